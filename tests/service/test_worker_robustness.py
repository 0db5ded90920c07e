"""Worker robustness on real Redis (and, where said, real workers, API and S3): finalising against a cancel, and
shards of a renderer no live worker has. The reconciler, other code versions and gzip shards:
tests/service/test_worker_reconcile.py."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from isolated_stacks import api_on, isolated, queued_tasks, record_only
from service_stack import Stack, tiny_spec, wait_for, wait_state, wait_worker_ready
from test_service_plumbing import FakeSession, make_ctx, new_dataset

from seasynth.service import __version__
from seasynth.service.queues import TASK_PLAN, TASK_RECONCILE, TASK_SHARD, shard_queue
from seasynth.service.records.store import Records
from seasynth.service.shards import manifest_key
from seasynth.service.storage import LocalStore
from seasynth.worker.queue.context import Outcome, WrongRenderer
from seasynth.worker.queue.finalise import maybe_finalise
from seasynth.worker.queue.pinning import RENDERER_LIVE_S, defer_to_renderer
from seasynth.worker.queue.shard import reconcile, run_shard, sweepable


@pytest.fixture
def records(infra):
    import redis

    r = redis.Redis.from_url(infra.settings().redis_url, decode_responses=True)
    yield Records(r, prefix=f"robust{time.monotonic_ns()}")
    r.close()


class Named(FakeSession):
    def __init__(self, name: str):
        super().__init__()
        self.renderer_name = name


CPU, GPU = "llvmpipe (fake)", "NVIDIA H100 (fake)"


# --- finalising and cancelling decide the state once, between them


class CancelOnManifest(LocalStore):
    """A bucket where a cancel arrives just as the manifest is written (the old finaliser's race window)."""

    def __init__(self, root: Path, records: Records, dataset_id: str):
        super().__init__(root)
        self.records, self.dataset_id, self.cancel_answers = records, dataset_id, []

    def put_bytes(self, key, data, content_type="application/octet-stream"):
        if key == manifest_key(self.dataset_id):
            self.cancel_answers.append(self.records.cancel(self.dataset_id, time.time()))
        super().put_bytes(key, data, content_type)


def test_a_cancel_while_the_manifest_is_written_finds_the_dataset_finished(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=4, shard_size=2)
    store = ctx.store = CancelOnManifest(tmp_path / "store", records, ds)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED and store.cancel_answers == []
    assert run_shard(ctx, ds, 1) is Outcome.COMMITTED
    # The state was decided before the manifest was written: the cancel lost, and both say succeeded.
    assert store.cancel_answers == ["succeeded"]
    rec = records.get(ds)
    manifest = json.loads(store.get_bytes(manifest_key(ds)))
    assert rec.state == manifest["state"] == "succeeded" and manifest["complete"]
    assert not records.manifest_pending(ds)


class CancelOnClaim(Records):
    """Records where a cancel arrives right after the finaliser claimed the dataset, before it decided."""

    def claim_finalise(self, dataset_id, ttl_s):
        claimed = super().claim_finalise(dataset_id, ttl_s)
        self.cancel(dataset_id, time.time())
        return claimed


def test_a_cancel_before_the_decision_leaves_no_manifest(infra, records, tmp_path):
    racing = CancelOnClaim(records._r, records._prefix)
    ctx = make_ctx(infra, racing, tmp_path, FakeSession())
    ds = new_dataset(racing, frames=2, shard_size=2)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED
    rec = racing.get(ds)
    assert (rec.state, rec.shards_done) == ("cancelled", 1)
    assert ctx.store.head(manifest_key(ds)) is None and not racing.manifest_pending(ds)
    assert maybe_finalise(ctx, ds) is False and ctx.store.head(manifest_key(ds)) is None


class RefuseManifestOnce(LocalStore):
    def __init__(self, root: Path):
        super().__init__(root)
        self.refused = 0

    def put_bytes(self, key, data, content_type="application/octet-stream"):
        if key.endswith("/manifest.json") and not self.refused:
            from seasynth.service.errors import Unavailable

            self.refused += 1
            raise Unavailable(f"storage unreachable writing {key}")
        super().put_bytes(key, data, content_type)


def test_a_manifest_the_bucket_refused_is_written_by_the_next_reconcile(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    store = ctx.store = RefuseManifestOnce(tmp_path / "store")
    ds = new_dataset(records, frames=2, shard_size=2)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED  # the shard's outcome stands
    assert store.refused == 1 and records.get(ds).state == "succeeded" and store.head(manifest_key(ds)) is None
    assert records.pending_manifests() == {ds}
    assert not records.is_finalising(ds), "a failed write gives the finalise lock back"
    assert reconcile(ctx, ds) == []
    manifest = json.loads(store.get_bytes(manifest_key(ds)))
    assert manifest["state"] == "succeeded" and [s["index"] for s in manifest["shards"]] == [0]
    assert records.pending_manifests() == set()
    assert maybe_finalise(ctx, ds) is False


# --- a dataset pinned to a renderer that no live worker has


def pinned(records: Records, renderer: str, frames: int = 6, shard_size: int = 2, dataset_id: str = "e" * 32) -> str:
    ds = new_dataset(records, frames=frames, shard_size=shard_size, dataset_id=dataset_id)
    assert records.set_renderer(ds, renderer) == renderer
    return ds


def hand_back(ctx, ds: str, index: int, now: float | None = None) -> Outcome:
    with pytest.raises(WrongRenderer) as wrong:
        run_shard(ctx, ds, index)
    return defer_to_renderer(ctx, ds, index, wrong.value, now=now)


def test_hand_backs_are_counted_shown_and_keep_the_dataset_from_stalling(infra, records, tmp_path):
    session = Named(CPU)
    ctx = make_ctx(infra, records, tmp_path, session)  # waits the stall timeout (SEASYNTH_RENDERER_WAIT_S unset)
    ds = pinned(records, GPU)
    records.touch(ds, time.time() - 10_000)
    for _ in range(3):
        assert hand_back(ctx, ds, 0) is Outcome.DEFERRED
    rec = records.get(ds)
    h = records._r.hgetall(records._key(ds))
    assert (rec.state, rec.attempts, rec.shards_done, session.calls) == ("queued", 0, 0, [])
    assert h["handbacks"] == "3" and time.time() - rec.touched_at < 5, "a hand-back is activity: no sweep"
    assert h["notice"].startswith(f"waiting for a shard worker with renderer {GPU!r}: none has run for ")
    assert h["notice"].endswith(f"; 3 hand-backs by workers running {CPU!r}")
    assert "fails if none comes within" in h["notice"]
    # A sweep leaves a shard that is going round alone, for a stall timeout after its last hand-back.
    now = time.time()
    assert reconcile(ctx, ds) == [1, 2]
    assert sweepable(ctx, ds, [0, 1, 2], now + ctx.settings.stall_s + 1) == [0, 1, 2]


def test_no_worker_of_the_renderer_for_the_wait_fails_the_dataset_naming_it(infra, records, tmp_path):
    gpu = make_ctx(infra, records, tmp_path, Named(GPU))
    cpu = make_ctx(infra, records, tmp_path, Named(CPU), renderer_wait_s=30)
    ds = new_dataset(records, frames=7, shard_size=2, dataset_id="f" * 32)
    assert run_shard(gpu, ds, 0) is Outcome.COMMITTED  # pins the dataset to the GPU, then the GPU workers leave
    t0 = time.time()
    assert hand_back(cpu, ds, 1, now=t0) is Outcome.DEFERRED
    assert hand_back(cpu, ds, 2, now=t0 + 29) is Outcome.DEFERRED
    attempts = records.get(ds).attempts
    assert hand_back(cpu, ds, 1, now=t0 + 30.5) is Outcome.FAILED
    rec = records.get(ds)
    assert (rec.state, rec.shards_done, rec.shards_failed, rec.attempts) == ("failed", 1, 3, attempts)
    assert set(rec.errors) == {1, 2, 3}
    for error in rec.errors.values():
        assert error.startswith(f"no shard worker with renderer {GPU!r}, which this dataset was started with, ran "
                                "for 30 s (the wait is 30 s, SEASYNTH_RENDERER_WAIT_S); workers running ")
        assert f"{CPU!r} handed its shards back 3 times" in error
    manifest = json.loads(gpu.store.get_bytes(manifest_key(ds)))
    assert manifest["state"] == "failed" and [s["index"] for s in manifest["shards"]] == [0]
    # Late copies of its shards change nothing.
    assert run_shard(cpu, ds, 2) is Outcome.FAILED and records.get(ds).attempts == attempts


def test_a_live_worker_of_the_renderer_keeps_the_dataset_waiting(infra, records, tmp_path):
    cpu = make_ctx(infra, records, tmp_path, Named(CPU), renderer_wait_s=30)
    ds = pinned(records, GPU)
    t0 = time.time()
    records.note_renderer(__version__, GPU, t0)  # a GPU worker's heartbeat
    assert hand_back(cpu, ds, 0, now=t0 + 1) is Outcome.DEFERRED
    h = records._r.hgetall(records._key(ds))
    assert "waiting_since" not in h and "one is running (all its processes busy)" in h["notice"]
    assert hand_back(cpu, ds, 0, now=t0 + RENDERER_LIVE_S - 1) is Outcome.DEFERRED
    # The heartbeats stop: the wait starts at the first hand-back that finds none, and runs out 30 s later.
    assert hand_back(cpu, ds, 0, now=t0 + RENDERER_LIVE_S) is Outcome.DEFERRED
    assert hand_back(cpu, ds, 0, now=t0 + RENDERER_LIVE_S + 29) is Outcome.DEFERRED
    assert hand_back(cpu, ds, 0, now=t0 + RENDERER_LIVE_S + 30) is Outcome.FAILED
    assert records.get(ds).state == "failed"


def test_a_worker_of_the_renderer_clears_the_notice(infra, records, tmp_path):
    cpu = make_ctx(infra, records, tmp_path, Named(CPU))
    gpu = make_ctx(infra, records, tmp_path, Named(GPU))
    ds = pinned(records, GPU, frames=2, shard_size=2)
    assert hand_back(cpu, ds, 0) is Outcome.DEFERRED
    assert run_shard(gpu, ds, 0) is Outcome.COMMITTED
    h = records._r.hgetall(records._key(ds))
    assert "notice" not in h and "waiting_since" not in h and h["state"] == "succeeded"
    assert records._r.hgetall(records._key(ds, "deferred")) == {}


def test_a_real_worker_hands_back_an_absent_renderers_shards_then_the_dataset_fails(stack: Stack):
    with isolated(stack, 11) as (env, services):
        ds = record_only(services, tiny_spec(frames=6, shard_size=2))
        services.records.set_renderer(ds, GPU)
        worker = stack.seasynth("worker-cpu-only", "worker", "--concurrency", "1", "--queues", "shards",
                                env={**env, "SEASYNTH_RENDERER_WAIT_S": "12"})
        try:
            wait_worker_ready(worker, 1)
            services.producer.send_task(TASK_PLAN, args=[ds, 0], queue=shard_queue(__version__))
            raw = services.raw_redis
            queue = shard_queue(__version__)

            def shard_messages() -> int:
                return sum(1 for task, args in queued_tasks(raw, queue) if task == TASK_SHARD and args[0] == ds)

            wait_for(lambda: int(services.records._r.hget(services.records._key(ds), "handbacks") or 0) >= 3, 30,
                     "three hand-backs")
            notice = services.records.get(ds).notice
            assert notice.startswith(f"waiting for a shard worker with renderer {GPU!r}: none has run for "), notice
            with api_on(services) as client:  # the status read says why nothing progresses
                shown = client.get(f"/datasets/{ds}").json()["notice"]
            assert shown.startswith(f"waiting for a shard worker with renderer {GPU!r}: none has run for "), shown
            # A forced sweep republishes none of the shards going round: still one message per shard.
            services.producer.send_task(TASK_RECONCILE, args=[ds, True], queue=queue)
            wait_for(lambda: not any(t != TASK_SHARD for t, _ in queued_tasks(raw, queue)), 20, "the sweep to run")
            # One process: at most one hand-back at a time publishes its copy just before its message is acked.
            counts = []
            for _ in range(12):
                counts.append(shard_messages())
                time.sleep(0.3)
            assert max(counts) <= 4 and min(counts) <= 3, counts
            with api_on(services) as client:
                final = wait_state(client, ds, {"failed", "succeeded"}, timeout=60)
            got = (final["state"], final["attempts"], final["shards_failed"], final["frames_done"])
            assert got == ("failed", 0, 3, 0), final
            assert [e["shard"] for e in final["errors"]] == [0, 1, 2]
            assert all(f"no shard worker with renderer {GPU!r}" in e["error"] for e in final["errors"])
            assert final["notice"].startswith(f"no shard worker with renderer {GPU!r}")
            assert "hand-back not recorded" not in worker.tail(400)
        finally:
            worker.stop()
