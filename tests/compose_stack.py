"""The compose stack as tests/test_compose.py drives it: docker-compose on a private engine, the API on the host's
published port, datasets posted and fetched as a user does (`seasynth fetch`), compared with a local `seasynth
generate` of the same spec, and the containers' records, metrics and health read through the engine."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import yaml
from prometheus_client.parser import text_string_to_metric_families

from seasynth.service.fetch import STATE_DIR
from tests.compose_engine import ROOT, Compose

EXAMPLE = ROOT / "examples" / "urchins.yaml"
WIDTH, HEIGHT = 160, 120
API = "http://localhost:8000"
PORTS = (8000, 9000, 9001, 5555)  # what docker-compose.yml publishes (Flower's on 127.0.0.1)
LOCAL_ONLY = {"seasynth.json", "manifest.json"}  # records beside the frames, not frame files


def spec(frames: int, shard_size: int) -> dict[str, Any]:
    """examples/urchins.yaml as POST /datasets takes it, with the local generate's --frames, --width, --height."""
    s = yaml.safe_load(EXAMPLE.read_text())
    s.update(frames=frames, shard_size=shard_size)
    s["camera"].update(width=WIDTH, height=HEIGHT)
    # The stack is under test, not the light: the water's closed form. The example's four Jerlov types under random
    # suns meet hundreds of unit columns to solve, and its first shards passed the three-minute task limit
    # (tests/compose.recovery.yml) on the 2-core machine while the other tests ran beside.
    s["water"]["solved_column"] = False
    return s


def cli(*args: str | Path, timeout: float = 600) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT)
    assert r.returncode == 0, f"seasynth {' '.join(map(str, args))}: {r.stdout[-2000:]}{r.stderr[-2000:]}"
    return r


def tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name not in LOCAL_ONLY and STATE_DIR not in p.parts}


def wait_for(pred: Callable[[], Any], timeout: float, what: str, interval: float = 1.0) -> Any:
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        try:
            last = pred()
        except (httpx.HTTPError, OSError, ValueError) as err:  # still starting
            last = err
        else:
            if last:
                return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what} (last: {last!r})")


def ports_in_use() -> list[int]:
    busy = []
    for port in PORTS:
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("0.0.0.0", port))
            except OSError:
                busy.append(port)
    return busy


class Stack:
    def __init__(self, compose: Compose, tmp: Path, workers: int):
        self.compose = compose
        self.workers = workers
        self.tmp = tmp
        self.http = httpx.Client(base_url=API, timeout=30)
        self.local: dict[int, dict[str, bytes]] = {}  # frames -> the local generate's tree
        self.finished: list[tuple[str, int]] = []  # (dataset id, frames) of succeeded datasets
        self.posts = 0

    def up(self) -> None:
        self.compose("up", "-d", "--no-build", "--scale", f"worker={self.workers}", timeout=900)
        self.wait_healthy()

    def wait_healthy(self, timeout: float = 420) -> None:
        """Until every service container runs and each with a health check is healthy (minio-init: exited 0)."""
        def states() -> dict[str, str]:
            out = {}
            for c in self.compose.containers():
                service = c["Config"]["Labels"]["com.docker.compose.service"]
                if service == "minio-init":
                    out[c["Name"]] = "done" if c["State"]["Status"] == "exited" and c["State"]["ExitCode"] == 0 \
                        else c["State"]["Status"]
                else:
                    out[c["Name"]] = c["State"].get("Health", {}).get("Status", c["State"]["Status"])
            return out

        seen: dict[str, str] = {}

        def all_healthy() -> bool:
            seen.clear()
            seen.update(states())
            return bool(seen) and all(s in ("healthy", "done") for s in seen.values())

        try:
            wait_for(all_healthy, timeout, "every container healthy", interval=3)
        except AssertionError:
            raise AssertionError(f"not healthy within {timeout} s: {seen}") from None
        wait_for(lambda: self.http.get("/readyz").status_code == 200, 60, "the API ready on the host's port 8000")

    def worker_containers(self, service: str = "worker") -> list[dict]:
        return [c for c in self.compose.containers(service) if c["State"]["Running"]]

    def reference(self, frames: int) -> dict[str, bytes]:
        """`seasynth generate` of the example at this size on this machine, the plain CLI a user runs."""
        if frames not in self.local:
            out, spec_file = self.tmp / f"local-{frames}", self.tmp / f"spec-{frames}.json"
            spec_file.write_text(json.dumps(spec(frames, shard_size=1)))  # a dataset's frames follow no shard size
            cli("generate", spec_file, "--out", out)
            self.local[frames] = tree(out)
        return self.local[frames]

    def post(self, frames: int, shard_size: int) -> str:
        r = self.http.post("/datasets", json=spec(frames, shard_size))
        assert r.status_code == 202, r.text
        self.posts += 1
        return r.json()["id"]

    def record(self, dataset_id: str) -> dict[str, Any]:
        r = self.http.get(f"/datasets/{dataset_id}")
        r.raise_for_status()
        return r.json()

    def wait_finished(self, dataset_id: str, timeout: float) -> dict[str, Any]:
        rec = wait_for(lambda: (r := self.record(dataset_id))["state"] in ("succeeded", "failed", "cancelled") and r,
                       timeout, f"dataset {dataset_id} to finish", interval=1)
        assert rec["state"] == "succeeded", rec
        return rec

    def fetch(self, dataset_id: str, name: str) -> dict[str, bytes]:
        out = self.tmp / name
        cli("fetch", dataset_id, "--out", out, "--api", API)
        return tree(out)

    def assert_complete(self, dataset_id: str, frames: int, shard_size: int, rec: dict[str, Any]) -> None:
        """Every frame exactly once, in the shards the plan made, and the bytes a local generate writes."""
        shards = -(-frames // shard_size)
        assert (rec["frames_done"], rec["frames_total"]) == (frames, frames), rec
        assert (rec["shards_done"], rec["shards_failed"], rec["shards_total"]) == (shards, 0, shards), rec
        assert rec["errors"] == [], rec["errors"]
        man = self.http.get(f"/datasets/{dataset_id}/manifest").json()
        assert man["complete"]
        assert [(s["first_frame"], s["frame_count"]) for s in man["shards"]] == [
            (i, min(shard_size, frames - i)) for i in range(0, frames, shard_size)]
        fetched = self.fetch(dataset_id, f"fetched-{dataset_id}")
        local = self.reference(frames)
        assert sorted(fetched) == sorted(local), "the fetched files differ from the local generate's by name"
        differing = [name for name in local if fetched[name] != local[name]]
        assert not differing, f"{len(differing)} of {len(local)} files differ from the local generate: {differing[:5]}"
        self.finished.append((dataset_id, frames))

    def running_on(self, dataset_id: str, host: str) -> list[int]:
        """Shards of the dataset that a render process on `host` has under way (the records' running hash)."""
        redis = self.compose.containers("redis")[0]["Id"]
        out = self.compose.engine.docker("exec", redis, "redis-cli", "HGETALL",
                                         f"seasynth:ds:{dataset_id}:running").stdout.split("\n")
        pairs = zip(out[0::2], out[1::2])
        return sorted(int(i) for i, who in pairs if who.strip() and json.loads(who)["host"] == host)

    def worker_metrics(self, container: dict) -> dict[str, float]:
        """A worker container's Prometheus samples (its port 9808 is not published: read from inside)."""
        text = self.compose.engine.docker(
            "exec", container["Id"], "python", "-c",
            "import urllib.request; print(urllib.request.urlopen('http://127.0.0.1:9808/metrics').read().decode())",
        ).stdout
        return samples(text)


def samples(text: str) -> dict[str, float]:
    """name{label="v",...} -> value, labels sorted."""
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            labels = ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items()))
            out[f"{s.name}{{{labels}}}" if labels else s.name] = s.value
    return out
