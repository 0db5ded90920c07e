"""The periodic reconciler, workers of another code version and gzip shards, on real Redis, Celery workers, API and
S3 (each on a Redis database of its own: tests/service/isolated_stacks.py)."""

from __future__ import annotations

import io
import sys
import tarfile
import threading
import time

from isolated_stacks import api_on, isolated, queued_tasks, record_only
from service_stack import Stack, tiny_spec, wait_for, wait_state, wait_worker_ready

from seasynth.service import __version__
from seasynth.service.queues import TASK_RECONCILE, TASK_SHARD, run_reconciler, shard_queue
from seasynth.service.records.coordination import pending_manifests_key
from seasynth.service.records.types import ShardCommit
from seasynth.service.shards import shard_key

# --- the periodic reconciler


def test_concurrent_reconcilers_sweep_each_stalled_dataset_once(stack: Stack, tmp_path):
    from seasynth.api.operations import sweep_all

    every = 0.5
    with isolated(stack, 12) as (env, services):
        stalled = [record_only(services, tiny_spec(), age_s=10_000) for _ in range(3)]
        fresh = record_only(services, tiny_spec())
        finished = record_only(services, tiny_spec())
        services.records.finish(finished, "succeeded", time.time())
        services.records._r.sadd(pending_manifests_key(services.records._prefix), finished)  # its manifest write failed
        from seasynth.api.deps import open_services

        peers = [open_services(services.settings) for _ in range(3)]
        stop, lines = threading.Event(), []
        threads = [threading.Thread(target=run_reconciler, args=(p, every, (lambda p=p: sweep_all(p))),
                                    kwargs={"stop": stop, "echo": lines.append, "alive": tmp_path / f"alive{i}"})
                   for i, p in enumerate(peers)]
        started = time.monotonic()
        [t.start() for t in threads]
        time.sleep(2.2)
        stop.set()
        [t.join(10) for t in threads]
        elapsed = time.monotonic() - started
        for p in peers:
            p.close()
        sent = [(t, args) for t, args in queued_tasks(services.raw_redis, shard_queue(__version__))]
        assert all(t == TASK_RECONCILE for t, _ in sent)
        # Each stalled dataset swept once (a per-dataset lock for a stall timeout), whatever the reconcilers.
        for ds in stalled:
            assert sent.count((TASK_RECONCILE, [ds, True])) == 1
        assert not [a for _, a in sent if a[0] == fresh]
        # One round per period among all three (the round lock): the pending manifest is nudged once a round.
        rounds = sent.count((TASK_RECONCILE, [finished, False]))
        assert 2 <= rounds <= int(elapsed / (0.8 * every)) + 1, (rounds, elapsed)
        assert sum("round failed" in line for line in lines) == 0
        assert sorted(line.split(":")[0] for line in lines if "publish again" in line) == sorted(stalled)
        # Each reconciler stays healthy, also the ones whose peers ran the rounds.
        assert all((tmp_path / f"alive{i}").exists() for i in range(3))


def test_a_failing_round_does_not_stop_the_reconciler(stack: Stack, tmp_path):
    calls = []

    def sweep() -> list[str]:
        calls.append(time.monotonic())
        if len(calls) == 1:
            raise ConnectionError("Redis went away")
        return []

    with isolated(stack, 13) as (_, services):
        stop, lines = threading.Event(), []
        thread = threading.Thread(target=run_reconciler, args=(services, 0.3, sweep),
                                  kwargs={"stop": stop, "echo": lines.append, "alive": tmp_path / "alive"})
        thread.start()
        wait_for(lambda: len(calls) >= 3, 10, "three rounds")
        stop.set()
        thread.join(5)
    assert not thread.is_alive() and lines[-1] == "reconciler: stopped"
    assert [line for line in lines if "round failed" in line] == [
        "reconciler: round failed, next in 0.3 s: ConnectionError: Redis went away"]
    assert (tmp_path / "alive").exists()


# --- a worker of another code version, gzip shards


OTHER_VERSION = "0.0.0-robustness"


def test_a_worker_of_another_version_republishes_a_shard_untouched_to_its_versions_queue(stack: Stack):
    with isolated(stack, 14) as (env, services):
        ds = record_only(services, tiny_spec(frames=4, shard_size=2))
        # A worker whose code says it is another version: it consumes that version's queue only.
        code = ("import sys; import seasynth.service as service; service.__version__ = sys.argv[1]; "
                "from seasynth.cli.main import main; "
                "sys.argv = ['seasynth', 'worker', '--concurrency', '1', '--queues', 'shards']; main()")
        worker = stack.start("worker-other-version", [sys.executable, "-c", code, OTHER_VERSION], env=env)
        try:
            wait_worker_ready(worker, 1)
            raw = services.raw_redis
            assert raw.llen(shard_queue(OTHER_VERSION)) == 0
            services.producer.send_task(TASK_SHARD, args=[ds, 1], queue=shard_queue(OTHER_VERSION))
            ours = shard_queue(__version__)
            wait_for(lambda: raw.llen(ours) == 1, 30, "the shard back on its version's queue")
            assert queued_tasks(raw, ours) == [(TASK_SHARD, [ds, 1])]
            assert raw.llen(shard_queue(OTHER_VERSION)) == 0
            rec = services.records.get(ds)
            assert (rec.state, rec.attempts, rec.renderer, rec.frames_done) == ("queued", 0, None, 0)
            assert services.records.tries(ds) == {} and services.records.running(ds) == {}
            assert f"Task {TASK_SHARD}" in worker.tail(200) and "'requeued'" in worker.tail(200)
        finally:
            worker.stop()


def test_gzip_shards_end_to_end(stack: Stack, tmp_path):
    from test_service_e2e import local_generate, tree

    from seasynth.service.fetch import fetch_dataset

    with isolated(stack, 15, shard_compression="gz") as (env, services):
        worker = stack.seasynth("worker-gz", "worker", "--concurrency", "1", "--queues", "shards,frames", env=env)
        try:
            wait_worker_ready(worker, 1)
            spec = tiny_spec(frames=5, shard_size=2)
            with api_on(services) as client:
                r = client.post("/datasets", json=spec)
                assert r.status_code == 202, r.text
                ds = r.json()["id"]
                final = wait_state(client, ds, {"succeeded", "failed"}, timeout=90)
                assert final["state"] == "succeeded", final
                man = client.get(f"/datasets/{ds}/manifest").json()
                assert [s["key"] for s in man["shards"]] == [shard_key(ds, i, "gz") for i in range(3)]
                members = []
                for s in man["shards"]:
                    data = services.store.get_bytes(s["key"])
                    assert data[:2] == b"\x1f\x8b" and len(data) == s["bytes"]
                    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
                        members += tar.getnames()
                assert len(members) == len(set(members)) == 5 * 4
                frame = client.get(f"/datasets/{ds}/frames/3")
                assert frame.status_code == 200
                base = str(client.base_url)
                fetched = tmp_path / "fetched"
                report = fetch_dataset(base, ds, fetched, progress=False)
            assert (report.shards_total, report.shards_fetched) == (3, 3)
            got = tree(fetched)
            assert set(got) == set(members) and got == local_generate(spec, tmp_path / "local")
            assert got["image_2/000003.png"] == frame.content
        finally:
            worker.stop()



def test_a_second_sweep_waits_until_the_queue_cannot_hold_the_pending_shards(stack: Stack):
    """A stalled dataset is swept once whatever the queue holds; after that, not while its shard queue has at least
    as many messages as it has pending shards (they may be its copies waiting behind a backlog), then again."""
    from seasynth.api.operations import sweep_if_stalled

    with isolated(stack, 13) as (_, services):
        version = "0.0.0+backlog"  # a queue no worker reads
        queue, records = shard_queue(version), services.records
        ds = record_only(services, tiny_spec(), age_s=10_000, version=version)  # 3 shards, none done
        services.raw_redis.rpush(queue, *[b"waiting"] * 5)  # another dataset's backlog
        assert sweep_if_stalled(services, records.get(ds), time.time()) and records.swept(ds)
        assert services.raw_redis.llen(queue) == 6  # the reconcile task joined the backlog
        records.release_sweep(ds)  # a stall timeout later
        assert not sweep_if_stalled(services, records.get(ds), time.time())
        assert records.claim_sweep(ds, 60)  # the lock was left alone
        records.release_sweep(ds)
        services.raw_redis.ltrim(queue, 0, 1)  # the backlog drains to 2 messages, fewer than the 3 pending shards
        assert sweep_if_stalled(services, records.get(ds), time.time())
        assert services.raw_redis.llen(queue) == 3
        # Every shard in, the finaliser gone: a sweep (its reconcile finalises) whatever the queue holds.
        records.release_sweep(ds)
        for i in range(3):
            records.commit(ds, ShardCommit(index=i, key=shard_key(ds, i), first_frame=2 * i, frame_count=2,
                                           sha256="0" * 64, bytes=1, code_version=version, renderer="test"))
        services.raw_redis.rpush(queue, *[b"waiting"] * 5)
        assert sweep_if_stalled(services, records.get(ds), time.time() + 2 * services.settings.stall_s)
