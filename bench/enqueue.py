"""How long `POST /datasets` takes to accept a 100,000-frame dataset: one record and one planner message,
whatever the frame count. Also times what the planner then does on a worker (bulk shard messages).

    python -m seasynth.bench.enqueue [--frames 100000] [--shard-size 50] [--repeats 20]

Uses SEASYNTH_REDIS_URL when set, else starts redis-server on a free port; storage is a local folder.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path


def _start_redis(folder: Path) -> tuple[subprocess.Popen, str]:
    import redis

    from seasynth.bench.stack import free_port

    port = free_port()
    proc = subprocess.Popen(
        ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
         "--maxmemory-policy", "noeviction", "--dir", str(folder)],
        stdout=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 10
    while True:
        try:
            redis.Redis(port=port).ping()
            return proc, f"redis://127.0.0.1:{port}/0"
        except redis.ConnectionError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def run(frames: int, shard_size: int, repeats: int) -> None:
    from celery import Celery
    from fastapi.testclient import TestClient

    from seasynth.api.main import create_app
    from seasynth.service.queues import TASK_SHARD, shard_queue
    from seasynth.service.settings import Settings

    with tempfile.TemporaryDirectory() as tmp:
        redis_proc = None
        url = os.environ.get("SEASYNTH_REDIS_URL")
        if not url:
            redis_proc, url = _start_redis(Path(tmp))
        try:
            settings = Settings(redis_url=url, storage="local", local_root=Path(tmp) / "store",
                                key_prefix=f"bench{os.getpid()}")
            spec = {"frames": frames, "shard_size": shard_size}
            times = []
            with TestClient(create_app(settings)) as client:
                client.post("/datasets", json=spec)  # warm-up: connections, first validation
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    r = client.post("/datasets", json=spec)
                    times.append(time.perf_counter() - t0)
                    assert r.status_code == 202, r.text
            shards = r.json()["shards_total"]

            # What the planner does on a worker: publish every shard message over one producer connection.
            app = Celery("bench", broker=url, set_as_current=False)
            queue = f"bench-{os.getpid()}-{shard_queue('x')}"
            t0 = time.perf_counter()
            with app.producer_or_acquire() as producer:
                for i in range(shards):
                    app.send_task(TASK_SHARD, args=["0" * 32, i], queue=queue, producer=producer)
            publish = time.perf_counter() - t0
        finally:
            if redis_proc is not None:
                redis_proc.terminate()
                redis_proc.wait(10)

    print(f"machine: {platform.node()} ({os.cpu_count()} CPUs, {platform.platform()})")
    print(f"POST /datasets, {frames} frames in {shards} shards of {shard_size}, {repeats} requests in-process:")
    print(f"  median {statistics.median(times) * 1e3:.1f} ms, max {max(times) * 1e3:.1f} ms")
    print(f"planner (on a worker, after the 202): {shards} shard messages published in {publish:.2f} s "
          f"({shards / publish:.0f}/s)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=100_000)
    p.add_argument("--shard-size", type=int, default=50)
    p.add_argument("--repeats", type=int, default=20)
    a = p.parse_args()
    run(a.frames, a.shard_size, a.repeats)


if __name__ == "__main__":
    main()
