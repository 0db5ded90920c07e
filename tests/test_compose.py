"""The compose stack built and run for real: stand-ins for the Docker Hub images (docker/standins/build.sh), the api
and worker images from their Dockerfiles, docker-compose.yml with docker/compose.standins.yml (and
tests/compose.recovery.yml's three-minute task limit) on a private Docker engine (tests/compose_engine.py). Datasets
posted to it come back byte-identical to a local `seasynth generate`, also across a worker crash, a Redis restart
and `down`/`up`; every container runs as non-root and turns healthy; Flower lists the workers; both /metrics answer.

Full size, CI's (18 min on the 2-core machine, the image builds most of it): 2 shard workers, 24- and 120-frame
datasets, a worker SIGKILLed and Redis restarted mid-run, the GPU worker image built and checked before the
stack is up (never run on a GPU: none here).
SEASYNTH_COMPOSE=reduced (14 min): one shard worker, an 8-frame dataset, no faults, no GPU image. With
SEASYNTH_COMPOSE_REPORT=FILE the run writes its timings and results there (`bash docker/standins/full-run.sh`:
bench/results/compose.md).

Skipped only where containers cannot run at all (not root, namespaces refused); a missing tool is a failure.
Host ports 8000, 9000, 9001 and 5555 must be free: docker-compose.yml publishes them.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import httpx
import pytest

from tests.compose_engine import Compose, DockerUnavailable, docker_engine, run
from tests.compose_report import Report
from tests.compose_stack import HEIGHT, PORTS, WIDTH, Stack, ports_in_use, samples, wait_for

FULL = os.environ.get("SEASYNTH_COMPOSE", "full") != "reduced"
REPORT_FILE = os.environ.get("SEASYNTH_COMPOSE_REPORT")
WORKERS = 2 if FULL else 1  # each worker container holds two whole copies of its 1 GB image (vfs)
FRAMES = 24 if FULL else 8  # the first dataset; the fault datasets have FAULT_FRAMES
FAULT_FRAMES = 120
FILES = ["docker-compose.yml", "docker/compose.standins.yml", "tests/compose.recovery.yml"]
PROJECT_SERVICES = {"api", "reconciler", "worker", "worker-frames"}  # built from docker/*.Dockerfile: uid 10001
PROJECT_UID = 10001

pytestmark = pytest.mark.timeout(3600)  # the stack fixture builds every image inside the first test's limit

full_only = pytest.mark.skipif(not FULL, reason="SEASYNTH_COMPOSE=reduced: the full size only (CI's)")

REPORT = Report()
GPU_IMAGE_CHECK: list[str] = []  # what gpu_image_check printed (full size only)


@pytest.fixture(scope="module")
def stack():
    busy = ports_in_use()
    assert not busy, f"host ports {busy} are in use; docker-compose.yml publishes {PORTS}: stop what holds them"
    folder = Path(tempfile.mkdtemp(prefix="seasynth-compose-"))
    tmp = Path(tempfile.mkdtemp(prefix="seasynth-compose-files-"))
    cleaning_from = None
    try:
        with docker_engine(folder / "engine") as engine:
            REPORT.facts["engine"] = run(["docker", "version", "--format", "dockerd {{.Server.Version}}"],
                                         engine.env, 60).stdout.strip()
            REPORT.facts["compose"] = run(["docker-compose", "version", "--short"], engine.env, 60).stdout.strip()
            built = REPORT.timed("stand-in images (docker/standins/build.sh)",
                                 lambda: run(["bash", "docker/standins/build.sh"], engine.env, 1800).stdout)
            for name, seconds in re.findall(r"build\.sh: (\S+) in (\d+) s", built):
                REPORT.timings[f"- stand-in {name}"] = float(seconds)
            compose = Compose(engine, "seasynth-test", FILES, profiles=["monitor"])
            REPORT.timed("api image (docker/api.Dockerfile)", lambda: compose("build", "api", timeout=1800))
            REPORT.timed("worker image (docker/worker.Dockerfile)", lambda: compose("build", "worker", timeout=1800))
            if FULL:  # built and checked before the stack is up, then removed (test_gpu_worker_image_builds)
                GPU_IMAGE_CHECK[:] = REPORT.timed("worker-gpu image (docker/worker-gpu.Dockerfile)",
                                                  lambda: gpu_image_check(compose))
            # Under vfs every layer is a whole copy and every container two more (its init and writable layers): the
            # untagged build stages and the GPU image go before the containers come.
            engine.docker("image", "prune", "--force")
            s = Stack(compose, tmp, WORKERS)
            try:
                REPORT.timed(f"up --scale worker={WORKERS}, every container healthy", s.up)
                yield s
            finally:
                s.http.close()
                cleaning_from = time.monotonic()
    except DockerUnavailable as why:
        pytest.skip(f"Docker cannot run here: {why}")
    finally:
        subprocess.run(["rm", "-rf", str(folder), str(tmp)], check=False)
        if cleaning_from is not None:
            REPORT.timings["clean-up: containers removed, dockerd stopped, its folder removed"] = \
                time.monotonic() - cleaning_from
        REPORT.timings["whole run"] = time.monotonic() - REPORT.t0
        if REPORT_FILE:
            REPORT.write(Path(REPORT_FILE), full=FULL, workers=WORKERS, size=(WIDTH, HEIGHT))


# --- the checks ----------------------------------------------------------------------------------------------------


def test_containers_non_root_and_healthy(stack: Stack):
    """Each service's main process runs as non-root (the project's as uid 10001), every health check is healthy,
    and `--scale` started the shard workers asked for."""
    containers = [c for c in stack.compose.containers() if c["State"]["Running"]]
    services = sorted({c["Config"]["Labels"]["com.docker.compose.service"] for c in containers})
    assert set(services) == PROJECT_SERVICES | {"redis", "minio", "flower"}, services
    assert len(stack.worker_containers()) == WORKERS
    uids = {}
    for c in containers:
        status = stack.compose.engine.docker("exec", c["Id"], "cat", "/proc/1/status").stdout
        real, effective, saved, fs = map(int, re.search(r"^Uid:\s+(.*)$", status, re.M).group(1).split())
        uids[c["Name"]] = effective
        assert 0 not in (real, effective, saved, fs), f"{c['Name']} runs as root: Uid {real} {effective} {saved} {fs}"
        if c["Config"]["Labels"]["com.docker.compose.service"] in PROJECT_SERVICES:
            assert effective == PROJECT_UID, (c["Name"], effective)
        assert c["State"]["Health"]["Status"] == "healthy", (c["Name"], c["State"]["Health"])
    REPORT.facts["uids"] = ", ".join(f"{n.lstrip('/')} {u}" for n, u in sorted(uids.items()))
    REPORT.passed["non-root, healthy"] = f"{len(containers)} containers"


def test_dataset_identical_to_local_generate(stack: Stack):
    """A dataset posted to the stack, fetched with `seasynth fetch`, is the local generate's files byte for byte;
    with several workers, more than one rendered it; both metrics endpoints count it."""
    shard_size = 2
    t0 = time.monotonic()
    dataset_id = stack.post(FRAMES, shard_size)
    rec = stack.wait_finished(dataset_id, 600)
    REPORT.timings[f"dataset of {FRAMES} frames ({WIDTH}x{HEIGHT}, shards of {shard_size}) rendered"] = \
        time.monotonic() - t0
    assert rec["attempts"] == rec["shards_total"], rec  # no fault: each shard ran once
    REPORT.timed(f"fetch + compare with a local generate ({FRAMES} frames)",
                 lambda: stack.assert_complete(dataset_id, FRAMES, shard_size, rec))

    # Worker metrics (each worker's own port, pool processes summed): the frames committed add up to the dataset's.
    per_worker = {c["Name"]: stack.worker_metrics(c).get('seasynth_worker_frames_total{outcome="committed"}', 0.0)
                  for c in stack.worker_containers()}
    assert sum(per_worker.values()) == FRAMES, per_worker
    if WORKERS > 1:
        assert sum(1 for n in per_worker.values() if n) >= 2, f"one worker rendered every shard: {per_worker}"
    # The API's own /metrics on the published port counts the POST.
    api = samples(stack.http.get("/metrics").text)
    assert api['seasynth_api_request_seconds_count{method="POST",route="/datasets",status="202"}'] == stack.posts
    REPORT.passed["byte-identical to local generate"] = (
        f"{FRAMES} frames, {len(stack.local[FRAMES])} files; frames committed per worker: "
        + ", ".join(f"{int(v)}" for v in per_worker.values()))
    REPORT.passed["both /metrics"] = "api :8000/metrics counts the POST; each worker's :9808 its frames"


@full_only
def test_worker_killed_mid_run(stack: Stack):
    """A worker container's main process SIGKILLed while it renders shards: Docker restarts it (restart:
    unless-stopped), those shards run again elsewhere, and the dataset completes with every frame once and the local
    generate's bytes."""
    shard_size = 4
    victim = stack.worker_containers()[0]
    host, restarts = victim["Config"]["Hostname"], victim["RestartCount"]
    t0 = time.monotonic()
    dataset_id = stack.post(FAULT_FRAMES, shard_size)
    wait_for(lambda: stack.record(dataset_id)["shards_done"] >= 2, 300, "2 shards committed", interval=0.3)
    held = wait_for(lambda: stack.running_on(dataset_id, host), 120, f"{host} to render a shard", interval=0.1)
    os.kill(victim["State"]["Pid"], signal.SIGKILL)
    rec = stack.wait_finished(dataset_id, 900)
    took = time.monotonic() - t0
    after = json.loads(stack.compose.engine.docker("inspect", victim["Id"]).stdout)[0]
    assert after["RestartCount"] == restarts + 1 and after["State"]["Running"], after["State"]
    assert rec["attempts"] > rec["shards_total"], f"no shard ran twice, yet {host} was rendering {held}: {rec}"
    stack.assert_complete(dataset_id, FAULT_FRAMES, shard_size, rec)
    REPORT.timings[f"dataset of {FAULT_FRAMES} frames, a worker SIGKILLed mid-run"] = took
    REPORT.passed["worker SIGKILLed mid-run"] = (
        f"killed while rendering shard(s) {held}; {rec['shards_total']} shards, {rec['attempts']} attempts; the "
        "container restarted; byte-identical")


@full_only
def test_redis_restarted_mid_run(stack: Stack):
    """Redis restarted mid-dataset (`docker-compose restart redis`: the append-only file keeps queue and records):
    the dataset completes with every frame once and the local generate's bytes."""
    shard_size = 4
    t0 = time.monotonic()
    dataset_id = stack.post(FAULT_FRAMES, shard_size)
    wait_for(lambda: stack.record(dataset_id)["shards_done"] >= 3, 300, "3 shards committed", interval=0.3)
    assert stack.record(dataset_id)["state"] == "running"
    stack.compose("restart", "redis")
    rec = stack.wait_finished(dataset_id, 900)
    took = time.monotonic() - t0
    stack.assert_complete(dataset_id, FAULT_FRAMES, shard_size, rec)
    REPORT.timings[f"dataset of {FAULT_FRAMES} frames, Redis restarted mid-run"] = took
    REPORT.passed["Redis restarted mid-run"] = (
        f"{rec['shards_total']} shards, {rec['attempts']} attempts; byte-identical")


def test_flower_lists_the_workers(stack: Stack):
    """Flower (profile monitor, on the workers' broker and visibility timeout) sees every running worker container
    online, shard and frame workers alike: their Celery node names end in the container's hostname."""
    running = {c["Config"]["Hostname"] for s in ("worker", "worker-frames") for c in stack.worker_containers(s)}

    def online() -> set[str]:
        data = httpx.get("http://localhost:5555/workers?json=1", timeout=10).json()["data"]
        return {w["hostname"].split("@", 1)[1] for w in data if w.get("status")}

    wait_for(lambda: online() == running, 120, f"Flower to list the workers {sorted(running)}", interval=2)
    REPORT.passed["Flower lists the workers"] = f"{len(running)} online (shard and frame workers)"


def test_down_up_keeps_datasets(stack: Stack):
    """`docker-compose down` then `up`: the finished datasets are still listed from Redis's volume (not rebuilt from
    the bucket) and fetch byte-identical from MinIO's."""
    assert stack.finished, "no dataset finished earlier in this run"
    REPORT.timed("down (volumes kept)", lambda: stack.compose("down", timeout=600))
    assert stack.compose.containers() == []
    REPORT.timed("up again, every container healthy", stack.up)
    listed = {d["id"]: d for d in stack.http.get("/datasets", params={"limit": 100}).json()["items"]}
    for dataset_id, frames in stack.finished:
        assert dataset_id in listed, f"{dataset_id} is not listed after down/up"
        assert listed[dataset_id]["state"] == "succeeded" and listed[dataset_id]["restored_at"] is None, \
            listed[dataset_id]
    dataset_id, frames = stack.finished[0]
    fetched = stack.fetch(dataset_id, f"fetched-again-{dataset_id}")
    assert fetched == stack.reference(frames)
    REPORT.passed["down/up keeps datasets"] = f"{len(stack.finished)} listed as before; one fetched byte-identical"


def gpu_image_check(compose: Compose) -> list[str]:
    """Builds the GPU worker image, runs `id -u`, its EGL vendor file and the CLI in it (no network), removes it, and
    returns the lines they printed."""
    compose("--profile", "gpu", "build", "worker-gpu", timeout=1800)
    image = "seasynth-worker-gpu:dev"
    out = compose.engine.docker(
        "run", "--rm", "--network", "none", image, "sh", "-c",
        "id -u && cat $__EGL_VENDOR_LIBRARY_FILENAMES && seasynth --help >/dev/null && echo cli-ok").stdout.split("\n")
    compose.engine.docker("rmi", image)
    return out


@full_only
def test_gpu_worker_image_builds(stack: Stack):
    """docker/worker-gpu.Dockerfile builds unchanged on the stand-in base; its entry point and NVIDIA EGL vendor file
    are in place and it runs as uid 10001. It cannot render here (no GPU, no NVIDIA container toolkit). The stack's
    fixture builds and runs it before the stack is up (gpu_image_check)."""
    out = GPU_IMAGE_CHECK
    assert out[0] == str(PROJECT_UID) and "libEGL_nvidia.so.0" in out[1] and out[2] == "cli-ok", out
    REPORT.passed["GPU worker image builds"] = "built; runs as uid 10001; not run on a GPU (none here)"
