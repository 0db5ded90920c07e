"""Infrastructure faults on the real stack: redis-server SIGKILLed and restarted (with its AOF, and empty), the
object store unreachable through a proxy (refused, reset, stalled), the API SIGKILLed while a client polls and
fetches, the reconciler SIGKILLed mid-round. Each dataset completes byte-identical to a local generate, every
frame exactly once, and a purged dataset leaves nothing."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
from faults import (
    FAULT_SHARDS,
    FAULT_SPEC,
    OUTAGE_ENV,
    SHORT_OUTAGE_ENV,
    FaultStack,
    assert_exact,
    children,
    close_fault_stack,
    objects_left,
    open_fault_stack,
    outage_s,
    record,
    verify_dataset,
    wait_done,
)
from service_stack import tiny_spec, wait_for

from seasynth.service import __version__
from seasynth.service.errors import Unavailable
from seasynth.service.queues import shard_queue


@pytest.fixture(scope="module")
def fstack(tmp_path_factory) -> Iterator[FaultStack]:
    st = open_fault_stack(tmp_path_factory.mktemp("faults-infra"))
    yield st
    close_fault_stack(st)


@pytest.fixture
def client(fstack: FaultStack) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=fstack.api_url, timeout=60) as c:
        yield c


def mid_dataset(st: FaultStack, client: httpx.Client, spec: dict = FAULT_SPEC) -> str:
    """A new dataset with its first shard committed and others still to come."""
    dataset_id = st.post(client, spec)
    wait_for(lambda: st.services.records.get(dataset_id).shards_done >= 1, 120, "a first shard", interval=0.01)
    return dataset_id


def purge_leaves_nothing(st: FaultStack, client: httpx.Client, dataset_id: str) -> int:
    """DELETE the dataset; how many of its objects are left (records/ included)."""
    assert client.delete(f"/datasets/{dataset_id}").status_code == 204
    left = objects_left(st, dataset_id) + sum(
        1 for o in st.services.store.list("records/") if dataset_id in o.key)
    assert left == 0
    return left


# --- Redis


def test_redis_sigkilled_and_restarted_with_its_aof(fstack: FaultStack, client, tmp_path):
    dataset_id = mid_dataset(fstack, client)
    fstack.kill_redis()
    time.sleep(1)
    fstack.start_redis()
    t0 = time.monotonic()
    final = wait_done(client, dataset_id, timeout=300)
    recover_s = time.monotonic() - t0
    assert final["state"] == "succeeded" and final["shards_failed"] == 0, final
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    left = purge_leaves_nothing(fstack, client, dataset_id)
    record("redis SIGKILL, AOF on", "redis-server SIGKILLed mid-dataset, restarted 1 s later on its AOF "
           "(--appendonly yes --appendfsync always)", verdict=v, recover_s=recover_s, left_behind=left,
           checked=["dataset succeeded with no failed shard", "purge leaves no object"])
    assert_exact(v, FAULT_SHARDS)


def test_redis_sigkilled_and_restarted_empty(fstack: FaultStack, client, tmp_path):
    """Redis comes back with nothing (persistence off, or a lost volume): records, queues and unacknowledged
    messages are gone. The periodic reconciler restores the dataset from the record its creation left in the
    bucket, adopts the committed shards' markers and republishes the rest; the record says it was restored. A
    finished dataset comes back finished (its manifest's state), a cancelled one cancelled, and neither renders."""
    finished = fstack.post(client, tiny_spec(frames=4, shard_size=2))
    assert wait_done(client, finished)["state"] == "succeeded"
    cancelled = fstack.post(client, FAULT_SPEC)
    assert client.post(f"/datasets/{cancelled}/cancel").json()["state"] == "cancelled"
    before = {i: client.get(f"/datasets/{i}").json() for i in (finished, cancelled)}
    before_manifest = client.get(f"/datasets/{finished}/manifest").json()
    dataset_id = mid_dataset(fstack, client)
    fstack.kill_redis()
    time.sleep(1)
    fstack.start_redis(wipe=True)
    t0 = time.monotonic()
    records = fstack.services.records
    # No status reads meanwhile: the reconciler alone must find the dataset.
    wait_for(lambda: records.get(dataset_id).state == "succeeded", 300, "the reconciler to restore and finish it",
             interval=0.5)
    recover_s = time.monotonic() - t0
    final = client.get(f"/datasets/{dataset_id}").json()
    assert final["state"] == "succeeded" and final["frames_done"] == FAULT_SPEC["frames"], final
    assert final["restored_at"] is not None, final
    for i, was in before.items():
        now = client.get(f"/datasets/{i}").json()
        same = ("state", "frames_done", "shards_done", "shards_total", "seed", "code_version", "created_at")
        assert {k: now[k] for k in same} == {k: was[k] for k in same} and now["restored_at"] is not None, (was, now)
    man = client.get(f"/datasets/{finished}/manifest").json()
    assert man["complete"] and [s["sha256"] for s in man["shards"]] == [
        s["sha256"] for s in before_manifest["shards"]]
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    left = purge_leaves_nothing(fstack, client, dataset_id)
    record("redis SIGKILL, restarted empty", "redis-server SIGKILLed mid-dataset and restarted with no data "
           "(persistence off / volume lost)", verdict=v, recover_s=recover_s, left_behind=left,
           checked=["the reconciler alone restored the record from the bucket (restored_at set) and finished it",
                    "purge leaves no object"])
    assert_exact(v, FAULT_SHARDS)


# --- the object store


@pytest.mark.parametrize("mode", ["refuse", "stall", "reset"])
def test_object_store_unreachable_mid_dataset(fstack: FaultStack, client, tmp_path, mode):
    """A dataset completes whole after the outage. With refuse and reset, a second dataset, still live, deleted
    during the outage is cancelled but its delete refused (503, still readable), deleted after the outage, and
    leaves no object once its shards' messages drain."""
    length = outage_s(OUTAGE_ENV, 30) if mode == "refuse" else outage_s(SHORT_OUTAGE_ENV, 10)
    dataset_id = mid_dataset(fstack, client)
    doomed = None if mode == "stall" else fstack.post(client, FAULT_SPEC)  # queued behind the first one's shards
    fstack.proxy.set(mode)
    if doomed is not None:
        # A pool process replaced during the outage (killed here; recycled after max tasks in production) opens
        # its resources without the bucket: its worker must stay up and open them on a later task.
        worker = fstack.workers()[0]
        [pool] = children(worker.popen.pid)
        os.kill(pool, signal.SIGKILL)
        wait_for(lambda: [p for p in children(worker.popen.pid) if p != pool], 30, "the replacement pool process")
        r = client.delete(f"/datasets/{doomed}")
        assert r.status_code == 503 and "unreachable" in r.json()["detail"], r.text
        assert client.get(f"/datasets/{doomed}").json()["state"] == "cancelled"
    time.sleep(length)
    during = fstack.services.records.get(dataset_id)
    fstack.proxy.set("pass")
    t0 = time.monotonic()
    final = wait_done(client, dataset_id, timeout=300)
    recover_s = time.monotonic() - t0
    assert final["state"] == "succeeded" and final["shards_failed"] == 0, final
    assert during.state == "running" and during.shards_done < FAULT_SHARDS, during
    assert len(fstack.workers()) == 2, [w.tail(20) for w in fstack.procs if w.name == "worker"]
    checked = ["no shard failed: an unreachable store does not use up a shard's attempts", "purge leaves no object",
               "both workers still up"]
    left = 0
    if doomed is not None:
        assert client.delete(f"/datasets/{doomed}").status_code == 204
        raw = fstack.services.raw_redis
        wait_for(lambda: raw.llen(shard_queue(__version__)) == 0 and raw.hlen("unacked") == 0, 120,
                 "the deleted dataset's shard messages to drain")
        left = objects_left(fstack, doomed) + sum(1 for o in fstack.services.store.list("records/") if doomed in o.key)
        checked.append("a dataset DELETEd during the outage: 503 and still readable; DELETEd after: no object "
                       "left once its shard messages drained")
        checked.append("a pool process SIGKILLed during the outage is replaced without the bucket; its worker "
                       "stays up")
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    left += purge_leaves_nothing(fstack, client, dataset_id)
    record(f"object store {mode}", f"every connection to S3 {_MODES[mode]} for {length:g} s mid-dataset (a TCP "
           "proxy in front of moto_server)", verdict=v, recover_s=recover_s, left_behind=left, checked=checked,
           outage_s=length)
    assert left == 0
    assert_exact(v, FAULT_SHARDS)


_MODES = {"refuse": "refused (ECONNREFUSED) and open ones reset", "stall": "accepted and held without a byte "
          "forwarded (a partition)", "reset": "reset (RST) on accept and open ones reset"}


# --- the API and the reconciler


def test_api_sigkilled_while_a_client_polls_and_fetches(fstack: FaultStack, client, tmp_path):
    from seasynth.service.fetch import fetch_dataset

    dataset_id = mid_dataset(fstack, client)
    url = fstack.api_url
    reads, refused, stop = [], [], threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=url, timeout=10) as c:
            while not stop.is_set():
                try:
                    c.get(f"/datasets/{dataset_id}").raise_for_status()
                    reads.append(time.monotonic())
                except httpx.TransportError:
                    refused.append(time.monotonic())
                time.sleep(0.1)

    poller = threading.Thread(target=poll)
    poller.start()
    out = tmp_path / "fetched"
    try:
        partial = fetch_dataset(url, dataset_id, out, partial=True, progress=False)
        assert partial.shards_fetched >= 1
        old = fstack.api_proc
        old.stop(signal.SIGKILL)
        t_kill = time.monotonic()
        with pytest.raises(Unavailable, match="cannot reach the API"):
            fetch_dataset(url, dataset_id, out, progress=False)
        wait_for(lambda: refused, 10, "the poller to see the API gone")
        fstack.api_proc = fstack.start_api_on(int(url.rsplit(":", 1)[1]))
        wait_for(lambda: reads[-1] > refused[-1], 30, "the poller to read again")
        recover_s = time.monotonic() - t_kill
        final = wait_done(client, dataset_id)
        assert final["state"] == "succeeded", final
    finally:
        stop.set()
        poller.join(15)
    report = fetch_dataset(url, dataset_id, out, progress=False)  # resumes: only the shards it lacked
    assert report.shards_skipped == partial.shards_fetched and report.shards_fetched == FAULT_SHARDS - \
        partial.shards_fetched
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    from test_service_e2e import tree

    assert tree(out) == tree(tmp_path / f"fetched-{dataset_id}")
    left = purge_leaves_nothing(fstack, client, dataset_id)
    record("API SIGKILL", "the API process SIGKILLed while a client polls status and fetches (partially), "
           "restarted on the same port", verdict=v, recover_s=recover_s, left_behind=left,
           checked=["a fetch during the outage fails with 'cannot reach the API'", "the resumed fetch downloads "
                    "only the shards it lacked and equals a fresh one", "purge leaves no object"])
    assert_exact(v, FAULT_SHARDS)


def test_reconciler_sigkilled_mid_round(fstack: FaultStack, client, tmp_path):
    """Redis comes back empty while the bucket stalls: the reconciler's round hangs listing the bucket's records
    and is SIGKILLed there; a new reconciler does the whole round again once the bucket answers."""
    dataset_id = mid_dataset(fstack, client)
    [old] = [p for p in fstack.procs if p.name == "reconciler" and p.popen.poll() is None]
    fstack.proxy.set("stall")
    fstack.kill_redis()
    fstack.start_redis(wipe=True)
    # Rounds come every second; one that got past Redis hangs listing the stalled bucket, its check unrecorded.
    time.sleep(4)
    records = fstack.services.records
    assert old.popen.poll() is None and records.seen_redis_run() is None
    assert not records.exists(dataset_id)
    old.stop(signal.SIGKILL)
    fstack.proxy.set("pass")
    fstack.start_reconciler(1.0)
    t0 = time.monotonic()
    wait_for(lambda: records.get(dataset_id).state == "succeeded", 300, "the new reconciler to restore it",
             interval=0.5)
    recover_s = time.monotonic() - t0
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    left = purge_leaves_nothing(fstack, client, dataset_id)
    record("reconciler SIGKILL mid-round", "the reconciler SIGKILLed while its round lists the bucket (Redis "
           "just restarted empty, the bucket stalled); a new one started", verdict=v, recover_s=recover_s,
           left_behind=left, checked=["the new reconciler restored and finished the dataset", "purge leaves no "
                                      "object"])
    assert_exact(v, FAULT_SHARDS)
