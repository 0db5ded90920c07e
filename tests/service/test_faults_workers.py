"""Worker faults on the real stack: a pool process SIGKILLed mid-shard, then a whole worker (main process and pool)
SIGKILLed mid-shard. Each dataset completes byte-identical to a local generate, every frame exactly once."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator

import httpx
import pytest
from faults import (
    FAULT_SHARDS,
    FAULT_SPEC,
    FaultStack,
    assert_exact,
    close_fault_stack,
    open_fault_stack,
    record,
    verify_dataset,
    wait_done,
)
from service_stack import wait_for, wait_worker_ready


@pytest.fixture(scope="module")
def fstack(tmp_path_factory) -> Iterator[FaultStack]:
    st = open_fault_stack(tmp_path_factory.mktemp("faults-workers"))
    yield st
    close_fault_stack(st)


@pytest.fixture
def client(fstack: FaultStack) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=fstack.api_url, timeout=60) as c:
        yield c


def caught_rendering(st: FaultStack, dataset_id: str) -> tuple[int, dict]:
    """A shard of the dataset that a process is rendering now, and who: {pid, host, since}."""
    return wait_for(lambda: next(iter(st.services.records.running(dataset_id).items()), None), 120,
                    "a shard to start rendering", interval=0.002)


def test_pool_process_sigkilled_mid_shard(fstack: FaultStack, client, tmp_path):
    dataset_id = fstack.post(client, FAULT_SPEC)
    shard, who = caught_rendering(fstack, dataset_id)
    os.kill(who["pid"], signal.SIGKILL)
    t_fault = time.monotonic()
    final = wait_done(client, dataset_id)
    recover_s = time.monotonic() - t_fault
    assert final["state"] == "succeeded", final
    tries = fstack.services.records.tries(dataset_id)
    # The killed execution and its rerun: one shard ran twice, every other once (the process may have moved on
    # from `shard` to its next one between the read and the kill).
    assert sorted(tries.values()) == [1] * (FAULT_SHARDS - 1) + [2], (shard, tries)
    assert final["attempts"] == FAULT_SHARDS + 1 and final["frames_done"] == FAULT_SPEC["frames"]
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    record("worker pool process SIGKILL", "SIGKILL of the pool process rendering a shard (Celery's main process "
           "lives on)", verdict=v, recover_s=recover_s, checked=["one shard ran exactly twice, the rest once"])
    assert_exact(v, FAULT_SHARDS)


def test_whole_worker_sigkilled_mid_shard_then_restarted(fstack: FaultStack, client, tmp_path):
    """The message the dead worker held stays unacknowledged in Redis (visibility timeout 3x the task limit); the
    other worker renders the rest, and the reconciler republishes the lost shard once the dataset has stalled
    (SEASYNTH_STALL_TIMEOUT_S, 60 s here) and the dead execution's lease is over. A restarted worker joins."""
    dataset_id = fstack.post(client, FAULT_SPEC)
    shard, who = caught_rendering(fstack, dataset_id)
    victim = next(w for w in fstack.workers() if _pool_of(w.popen.pid, who["pid"]))
    os.killpg(victim.popen.pid, signal.SIGKILL)  # the worker's session: main process and pool
    victim.popen.wait(10)
    t_fault = time.monotonic()
    wait_worker_ready(fstack.start_worker(1), 1)  # the restarted worker
    final = wait_done(client, dataset_id, timeout=300)
    recover_s = time.monotonic() - t_fault
    assert final["state"] == "succeeded", final
    tries = fstack.services.records.tries(dataset_id)
    assert sorted(tries.values()) == [1] * (FAULT_SHARDS - 1) + [2], (shard, tries)
    v = verify_dataset(fstack, dataset_id, FAULT_SPEC, tmp_path)
    record("whole worker SIGKILL", "SIGKILL of a worker's main process and its pool process mid-shard; a new "
           "worker started", verdict=v, recover_s=recover_s,
           checked=["one shard ran exactly twice (its message was lost with the worker: the reconciler "
                    "republished it after the stall timeout)"])
    assert_exact(v, FAULT_SHARDS)


def _pool_of(parent: int, pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1]) == parent
    except OSError:
        return False
