"""One `mode: service` row of seasynth.bench.scale: a spec rendered by the real service on this machine (seasynth.bench.stack:
redis-server, an S3 server on loopback, the API, one `seasynth worker` whose prefork pool has `workers` processes),
submitted as a user does (POST /datasets) and followed through GET /datasets/{id}.

The workers are started, and their renderers opened, before the clock starts: a service's workers are long-lived,
so a dataset does not pay their start-up. wall_fps runs from the POST to the status read that says succeeded;
shard completions are seen by polling the status every POLL_S, which bounds the resolution of first_frame_s and
steady_fps.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from seasynth.bench.meters import CpuMeter, GpuSampler, rates
from seasynth.service.gpus import GpuChoice
from seasynth.service.spec.dataset import MAX_SHARD_MEGAPIXELS, DatasetSpec

POLL_S = 0.1
SHARDS_PER_WORKER = 5  # several shards per process, so shard completions spread over the run
TASK_TIME_LIMIT_S = 3600  # room for large shards at 1080p on a slow worker (admission estimates a shard's time)


def service_shard_size(frames_per_worker: int, pixels_per_frame: int = 0) -> int:
    """A fifth of a worker's frames a shard, within the spec's shard limit (MAX_SHARD_MEGAPIXELS) at
    `pixels_per_frame`."""
    size = max(1, math.ceil(frames_per_worker / SHARDS_PER_WORKER))
    if pixels_per_frame > 0:
        size = min(size, max(1, int(MAX_SHARD_MEGAPIXELS * 1e6 // pixels_per_frame)))
    return size


def run_service(spec: DatasetSpec, workers: int, platform: str, gpus: GpuChoice | None,
                storage: str = "s3") -> dict[str, Any]:
    """frames, wall and steady fps, utilisation, and frames_stored (what the bucket holds) of one service run."""
    from seasynth.bench.stack import local_stack

    worker_env = {"SEASYNTH_GL_PLATFORM": platform, **({"SEASYNTH_GPUS": str(gpus)} if gpus is not None else {})}
    body = spec.model_dump(mode="json")
    with tempfile.TemporaryDirectory(prefix="seasynth-scale-") as tmp, local_stack(
        Path(tmp), concurrency=workers, worker_env=worker_env, storage=storage,
        extra_env={"SEASYNTH_TASK_TIME_LIMIT_S": str(TASK_TIME_LIMIT_S)},
    ) as stack, httpx.Client(base_url=stack.api, headers=stack.headers, timeout=30) as client:
        stamps: list[float] = []
        with GpuSampler() as gpu, CpuMeter() as cpu:
            t0 = time.perf_counter()
            r = client.post("/datasets", json=body)
            if r.status_code != 202:
                raise RuntimeError(f"POST /datasets answered {r.status_code}: {r.text}")
            dataset_id = r.json()["id"]
            status = follow(client, dataset_id, stamps, timeout_s=600 + 10.0 * spec.frames)
            wall = time.perf_counter() - t0
        if status["state"] != "succeeded":
            raise RuntimeError(f"dataset {dataset_id} ended {status['state']}: {status.get('errors')}\n"
                               f"worker log:\n{stack.log('worker')}")
        stored = frames_stored(stack.store(), dataset_id)
    return {"frames": status["frames_done"], "frames_stored": stored, "shard_size": spec.shard_size,
            **rates(stamps, t0, wall), "gpu_util": gpu.mean(), "cpu_util": cpu.util}


def follow(client: httpx.Client, dataset_id: str, stamps: list[float], timeout_s: float) -> dict[str, Any]:
    """Poll the dataset's status until it is final; one time stamp in `stamps` per frame, when its shard was seen
    committed. Returns the final status."""
    seen, deadline = 0, time.monotonic() + timeout_s
    while True:
        status = client.get(f"/datasets/{dataset_id}").raise_for_status().json()
        now = time.perf_counter()
        if status["frames_done"] > seen:
            stamps.extend([now] * (status["frames_done"] - seen))
            seen = status["frames_done"]
        if status["state"] in ("succeeded", "failed", "cancelled"):
            return status
        if time.monotonic() > deadline:
            raise TimeoutError(f"dataset {dataset_id} not finished after {timeout_s:.0f} s: {status}")
        time.sleep(POLL_S)


def frames_stored(store, dataset_id: str) -> int:
    """Frames in the bucket: the stored manifest's frame counts over the shards whose tar is there with the size
    the manifest gives (the tars are not read back: at 1080p that would be gigabytes)."""
    from seasynth.bench.stack import wait
    from seasynth.service.shards import manifest_key

    # manifest.json is written just after the dataset is marked finished
    wait(lambda: store.head(manifest_key(dataset_id)), 30, f"manifest.json of dataset {dataset_id}")
    manifest = json.loads(store.get_bytes(manifest_key(dataset_id)))
    sizes = {o.key: o.bytes for o in store.list(f"datasets/{dataset_id}/shards/")}
    return sum(s["frame_count"] for s in manifest["shards"] if sizes.get(s["key"]) == s["bytes"])
