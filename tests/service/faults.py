"""Fault injection over real components: a TCP proxy that passes, refuses, resets or stalls connections, a whole
service stack of its own (Redis with AOF, moto behind the proxy, workers, API, reconciler) and the checks every
fault scenario ends with (the fetched dataset equals a local generate, each frame exactly once, nothing left of a
purged dataset), plus the record a scenario appends for bench.reliability."""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import socket
import tarfile
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from service_stack import BUCKET, Proc, Stack, free_port, need, tiny_spec, wait_for, wait_state

RESULTS_ENV = "SEASYNTH_RELIABILITY_OUT"  # a JSON-lines file each scenario appends its record to
OUTAGE_ENV = "SEASYNTH_FAULT_OUTAGE_S"  # the object store outage of the refuse scenario (default 30 s)
SHORT_OUTAGE_ENV = "SEASYNTH_FAULT_SHORT_OUTAGE_S"  # the stall and reset outages (default 10 s)

# The fault scenarios' dataset: 8 shards of 2 frames, each frame ~50 ms on llvmpipe, so that a shard is caught
# mid-render by polling its running entry.
FAULT_SPEC = tiny_spec(frames=16, shard_size=2, camera={"width": 160, "height": 120}, quality="high",
                       terrain={"cells": 96, "variants": 1})
FAULT_SHARDS = 8
FRAME_FILES = 4  # image_2, label_2, calib, meta per frame


def outage_s(env: str, default: float) -> float:
    return float(os.environ.get(env, "") or default)


# --- a fault-injecting TCP proxy


class FaultProxy:
    """A TCP proxy on 127.0.0.1:port to `target`, with real sockets.

    Modes: "pass" forwards; "refuse" closes the listening socket and resets every open connection (new ones get
    ECONNREFUSED); "reset" accepts and resets at once, and resets every open connection; "stall" accepts and
    forwards nothing, holding open connections as they are (a partition): back in "pass", held connections
    resume and held new ones are connected through.
    """

    def __init__(self, target: tuple[str, int]):
        self.target = target
        self.port = free_port()
        self.mode = "pass"
        self._lock = threading.Lock()
        self._flowing = threading.Event()
        self._flowing.set()
        self._conns: set[socket.socket] = set()
        self._doomed: set[socket.socket] = set()  # reset: closed with an RST once their pump wakes
        self._listener: socket.socket | None = None
        self._closed = False
        self.accepted = 0
        self._listen()

    def _listen(self) -> None:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", self.port))
        s.listen(64)
        self._listener = s
        threading.Thread(target=self._accept, args=(s,), daemon=True).start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def set(self, mode: str) -> None:
        assert mode in ("pass", "refuse", "reset", "stall"), mode
        with self._lock:
            self.mode = mode
            if mode == "stall":
                self._flowing.clear()
            if mode in ("refuse", "reset"):
                self._reset_all()
            if mode == "refuse" and self._listener is not None:
                self._listener.close()
                self._listener = None
            if mode != "refuse" and self._listener is None:
                self._listen()
            if mode == "pass":
                self._flowing.set()

    def close(self) -> None:
        self._closed = True
        self.set("refuse")
        self._flowing.set()

    def _reset_all(self) -> None:
        for c in list(self._conns):
            self._doomed.add(c)
            _reset(c)
        self._conns.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:  # closed: refuse mode or the end
                return
            self.accepted += 1
            if self.mode == "reset" or self._closed:
                _reset_now(client)
                continue
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        with self._lock:
            self._conns.add(client)
        self._flowing.wait()  # a connection accepted during a stall is connected through once it ends
        if self.mode in ("reset", "refuse") or self._closed:
            _reset_now(client)
            return
        try:
            upstream = socket.create_connection(self.target, timeout=10)
        except OSError:
            _reset_now(client)
            return
        upstream.settimeout(None)
        with self._lock:
            self._conns.add(upstream)
        threading.Thread(target=self._pump, args=(upstream, client), daemon=True).start()
        self._pump(client, upstream)

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                data = src.recv(65536)
                self._flowing.wait()  # a stall holds what arrived until the partition heals
                if not data or src not in self._conns:
                    break
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                with self._lock:
                    self._conns.discard(s)
                if s not in self._doomed:  # a reset socket closes without a FIN: its linger sends the RST
                    try:
                        s.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                s.close()


def _reset_now(s: socket.socket) -> None:
    """Reset a socket no thread reads."""
    _reset(s)
    s.close()


def _reset(s: socket.socket) -> None:
    """Reset: SO_LINGER 0, so that closing sends an RST rather than a FIN. A thread blocked in recv() on it would
    hold the socket open through close(); shutting down its read side wakes that thread, which closes it."""
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        s.shutdown(socket.SHUT_RD)
    except OSError:
        pass


# --- a service stack of the fault suite's own


# Short limits so that recovery paths run within the suite's time: a lost shard is swept after 60 s of stall
# (the least SEASYNTH_STALL_TIMEOUT_S allows), a lost execution's lease is 60 s.
FAULT_ENV = {
    "SEASYNTH_TASK_TIME_LIMIT_S": "60",
    "SEASYNTH_STALL_TIMEOUT_S": "60",
    "SEASYNTH_FRAME_TIMEOUT_S": "30",
    "SEASYNTH_WORKER_SOFT_SHUTDOWN_S": "2",
}


@dataclass
class FaultStack(Stack):
    redis_port: int = 0
    redis_dir: Path | None = None
    redis_proc: Proc | None = None
    s3_port: int = 0
    proxy: FaultProxy | None = None
    services: Any = None

    def start_redis(self, *, wipe: bool = False) -> Proc:
        """redis-server as compose runs it (AOF on), fsync on every write; `wipe` first empties its folder (a
        restart that lost everything: persistence off, or a lost volume)."""
        if wipe:
            shutil.rmtree(self.redis_dir, ignore_errors=True)
        self.redis_dir.mkdir(parents=True, exist_ok=True)
        self.redis_proc = self.start("redis", [
            need("redis-server"), "--port", str(self.redis_port), "--bind", "127.0.0.1", "--save", "",
            "--appendonly", "yes", "--appendfsync", "always", "--maxmemory-policy", "noeviction",
            "--dir", str(self.redis_dir)])
        import redis as redis_py

        wait_for(lambda: redis_py.Redis(port=self.redis_port).ping(), 30, "redis-server")
        return self.redis_proc

    def kill_redis(self) -> None:
        self.redis_proc.stop(signal.SIGKILL)

    def start_api_on(self, port: int) -> Proc:
        """An API on a given port (a restart where clients already point)."""
        proc = self.seasynth("api", "serve", "--host", "127.0.0.1", "--port", str(port))
        wait_for(lambda: httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200, 60, "the API")
        return proc

    def start_reconciler(self, every_s: float = 1.0) -> Proc:
        return self.seasynth("reconciler", "reconcile", "--every", str(every_s))

    def post(self, client: httpx.Client, spec: dict) -> str:
        r = client.post("/datasets", json=spec)
        assert r.status_code == 202, r.text
        return r.json()["id"]


def open_fault_stack(tmp: Path, workers: int = 2) -> FaultStack:
    redis_port, s3_port = free_port(), free_port()
    st = FaultStack(tmp, {}, redis_port=redis_port, redis_dir=tmp / "redis", s3_port=s3_port)
    st.proxy = FaultProxy(("127.0.0.1", s3_port))
    st.env = {
        **{k: v for k, v in os.environ.items() if not k.startswith(("SEASYNTH_", "AWS_"))},
        **FAULT_ENV,
        "SEASYNTH_REDIS_URL": f"redis://127.0.0.1:{redis_port}/0",
        "SEASYNTH_S3_ENDPOINT_URL": st.proxy.url,  # every component reaches the bucket through the proxy
        "SEASYNTH_S3_BUCKET": BUCKET,
        "SEASYNTH_S3_CREATE_BUCKET": "true",
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "PYTHONUNBUFFERED": "1",
    }
    st.start_redis()
    st.start("s3", [need("moto_server"), "-H", "127.0.0.1", "-p", str(s3_port)])
    wait_for(lambda: httpx.get(f"http://127.0.0.1:{s3_port}", timeout=2).status_code < 500, 30, "moto_server")
    os.environ.update({k: st.env[k] for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION")})
    from seasynth.api.deps import open_services

    # The suite's own view of the bucket goes around the proxy: checks must not depend on the fault.
    st.services = open_services(st.settings(s3_endpoint_url=f"http://127.0.0.1:{s3_port}"))
    st.api_proc, st.api_url = st.start_api()
    from service_stack import wait_worker_ready

    for _ in range(workers):
        wait_worker_ready(st.start_worker(1), 1)
    st.start_reconciler(1.0)  # as compose and the k8s manifests deploy it, with a shorter period
    # Its first round notes which Redis process it checked (a restart is noticed against that).
    wait_for(lambda: st.services.records.seen_redis_run(), 60, "the reconciler's first round")
    return st


def close_fault_stack(st: FaultStack) -> None:
    """SIGKILL every component's process group (each started in a session of its own: a worker's pool goes with
    it), whatever state the faults left it in."""
    for p in reversed(st.procs):
        try:
            os.killpg(p.popen.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    for p in st.procs:
        try:
            p.popen.wait(10)
        except Exception:  # noqa: BLE001 - a process that outlives SIGKILL is the OS's; the next one is still reaped
            continue
    st.services.close()
    st.proxy.close()


# --- the checks every scenario ends with


_REFERENCE: dict[str, dict[str, bytes]] = {}


def reference(spec: dict, tmp: Path) -> dict[str, bytes]:
    """A local `seasynth generate` of `spec` (once per test process)."""
    from test_service_e2e import local_generate

    key = json.dumps(spec, sort_keys=True)
    if key not in _REFERENCE:
        _REFERENCE[key] = local_generate(spec, tmp / f"reference-{len(_REFERENCE)}")
    return _REFERENCE[key]


@dataclass
class Verdict:
    """What the end of a scenario found."""

    frames_expected: int
    frames_lost: int
    frames_duplicated: int
    shard_objects: int  # shard tars in the bucket
    markers: int  # commit markers in the bucket
    identical: bool  # the fetched tree equals the local generate, file for file
    checked: list[str] = field(default_factory=list)
    differing: list[str] = field(default_factory=list)  # files missing, extra or unequal (the first 20)


def verify_dataset(st: FaultStack, dataset_id: str, spec: dict, tmp: Path) -> Verdict:
    """Fetch the dataset through the API and compare it with a local generate; count frames in the manifest, the
    shard tars and the bucket listing."""
    from test_service_e2e import tree

    from seasynth.service.fetch import fetch_dataset

    store = st.services.store
    frames = spec["frames"]
    man = httpx.get(f"{st.api_url}/datasets/{dataset_id}/manifest", timeout=60).json()
    listed = [o.key for o in store.list(f"datasets/{dataset_id}/")]
    tars = [k for k in listed if k.endswith((".tar", ".tar.gz"))]
    markers = [k for k in listed if "/commits/" in k]
    members: Counter[str] = Counter()
    for s in man["shards"]:
        with tarfile.open(fileobj=io.BytesIO(store.get_bytes(s["key"]))) as tar:
            members.update(tar.getnames())
    seen_frames = Counter(int(Path(n).stem) for n in members if n.startswith("image_2/"))
    lost = sum(1 for i in range(frames) if seen_frames[i] == 0)
    duplicated = sum(n - 1 for n in seen_frames.values() if n > 1) + sum(n - 1 for n in members.values() if n > 1)
    fetched = tmp / f"fetched-{dataset_id}"
    fetch_dataset(st.api_url, dataset_id, fetched, progress=False)
    got, want = tree(fetched), reference(spec, tmp)
    identical = got == want
    differing = sorted(n for n in set(got) | set(want) if got.get(n) != want.get(n))[:20]
    return Verdict(frames, lost, duplicated, len(tars), len(markers), identical, differing=differing, checked=[
        "fetched tree == local generate (every file but seasynth.json/manifest.json)",
        "manifest complete; each frame's files in exactly one shard tar",
        "bucket: one tar and one commit marker per shard",
    ])


def assert_exact(v: Verdict, shards: int) -> None:
    assert (v.frames_lost, v.frames_duplicated) == (0, 0), v
    assert (v.shard_objects, v.markers) == (shards, shards), v
    assert v.identical, v


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid` (a worker's pool processes)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, IndexError, ValueError):
                continue
    return out


def objects_left(st: FaultStack, dataset_id: str) -> int:
    return sum(1 for _ in st.services.store.list(f"datasets/{dataset_id}/"))


def record(scenario: str, fault: str, *, verdict: Verdict | None = None, recover_s: float | None = None,
           left_behind: int | None = 0, outcome: str = "passed", note: str = "", checked: list[str] | None = None,
           **extra: Any) -> None:
    """Append the scenario's record to $SEASYNTH_RELIABILITY_OUT (no file named: nothing to do)."""
    path = os.environ.get(RESULTS_ENV)
    if not path:
        return
    row = {
        "scenario": scenario, "fault": fault, "outcome": outcome,
        "checked": (checked or []) + (verdict.checked if verdict else []),
        "frames_lost": None if verdict is None else verdict.frames_lost,
        "frames_duplicated": None if verdict is None else verdict.frames_duplicated,
        "identical": None if verdict is None else verdict.identical,
        "recover_s": None if recover_s is None else round(recover_s, 1),
        "objects_left_behind": left_behind, "note": note, **extra,
    }
    with open(path, "a") as f:
        f.write(json.dumps(row) + "\n")


def wait_done(client: httpx.Client, dataset_id: str, timeout: float = 240) -> dict[str, Any]:
    return wait_state(client, dataset_id, {"succeeded", "failed", "cancelled"}, timeout=timeout)
