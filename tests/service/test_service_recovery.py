"""Recovery with real components: a worker without a renderer takes no work, and the reconciler republishes
shards whose messages were lost (through status reads and `seasynth reconcile`)."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from service_stack import Stack, tiny_spec, wait_state

from seasynth.service import __version__
from seasynth.service.queues import TASK_SHARD, shard_queue
from seasynth.service.records.store import Records
from seasynth.service.shards import shard_count
from seasynth.service.spec.dataset import parse_spec


def record_only(records: Records, spec: dict, *, age_s: float) -> str:
    """A dataset recorded as the API does, whose planner message was lost; last touched age_s ago."""
    import uuid

    s = parse_spec(spec)
    dataset_id = uuid.uuid4().hex
    records.create(dataset_id, s.model_dump(mode="json"), seed=s.seed, code_version=__version__, frames=s.frames,
                   shard_size=s.shard_size, shards=shard_count(s.frames, s.shard_size), now=time.time() - age_s)
    return dataset_id


def test_worker_without_a_renderer_takes_no_shards(stack: Stack):
    """GL fails to start: the worker stops with an error and every shard stays queued, no attempt used."""
    import redis

    from seasynth.api.deps import open_services

    # A Redis database of its own, so the healthy workers of the session do not take these shards first.
    url = stack.settings().redis_url.rsplit("/", 1)[0] + "/3"
    services = open_services(stack.settings(redis_url=url))
    raw = redis.Redis.from_url(url)
    try:
        raw.flushdb()
        dataset_id = record_only(services.records, tiny_spec(frames=3, shard_size=1), age_s=0)
        for i in range(3):
            services.producer.send_task(TASK_SHARD, args=[dataset_id, i], queue=shard_queue(__version__))
        worker = stack.seasynth("worker-nogl", "worker", "--concurrency", "2", env={
            "SEASYNTH_REDIS_URL": url, "PYOPENGL_PLATFORM": "egl",
            "__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent/no-such-vendor.json",
        })
        try:
            code = worker.popen.wait(60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"a worker without a renderer kept running:\n{worker.tail()}")
        log = worker.tail(200)
        assert code == 1 and "render session failed to open" in log, log
        assert raw.llen(shard_queue(__version__)) == 3 and raw.hlen("unacked") == 0, log
        rec = services.records.get(dataset_id)
        assert (rec.state, rec.attempts, rec.renderer) == ("queued", 0, None)
    finally:
        raw.flushdb()
        raw.close()
        services.close()


def test_status_reads_republish_lost_shards(stack: Stack, client, services):
    # Lost planner message, stalled long ago: the next status read sends the reconciler.
    lost = record_only(services.records, tiny_spec(frames=4, shard_size=2), age_s=10_000)
    assert client.get(f"/datasets/{lost}").json()["state"] == "queued"
    final = wait_state(client, lost, {"succeeded", "failed"}, timeout=60)
    assert final["state"] == "succeeded" and (final["frames_done"], final["attempts"]) == (4, 2), final

    # A shard that looks running within its lease holds the sweep back; once the lease is over it is republished.
    held = record_only(services.records, tiny_spec(frames=2, shard_size=2), age_s=10_000)
    services.records.start_attempt(held, 0, 3, {"pid": 1, "host": "gone", "since": time.time()})
    services.records.touch(held, time.time() - 10_000)
    assert client.get(f"/datasets/{held}").json()["state"] == "running"
    time.sleep(1.5)
    assert services.records.get(held).shards_done == 0 and not services.records.is_finalising(held)
    lease = stack.settings().running_lease_s
    services.records.start_attempt(held, 0, 3, {"pid": 1, "host": "gone", "since": time.time() - lease - 1})
    services.records.touch(held, time.time() - 10_000)
    final = wait_state(client, held, {"succeeded", "failed"}, timeout=60)
    assert final["state"] == "succeeded" and final["attempts"] == 3, final  # two lost executions, one real


def test_reconcile_command_sweeps_stalled_datasets_only(stack: Stack, client, services):
    stalled = record_only(services.records, tiny_spec(frames=2, shard_size=1), age_s=10_000)
    fresh = record_only(services.records, tiny_spec(frames=2, shard_size=1), age_s=0)
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "reconcile"], capture_output=True, text=True,
                       timeout=60, env=stack.env)
    assert r.returncode == 0, r.stderr
    assert stalled in r.stdout and fresh not in r.stdout
    assert wait_state(client, stalled, {"succeeded", "failed"}, timeout=60)["state"] == "succeeded"
    assert services.records.get(fresh).state == "queued"
    # Named datasets are swept at once, stalled or not.
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "reconcile", fresh], capture_output=True, text=True,
                       timeout=60, env=stack.env)
    assert r.returncode == 0 and fresh in r.stdout, r.stderr
    assert wait_state(client, fresh, {"succeeded", "failed"}, timeout=60)["state"] == "succeeded"
