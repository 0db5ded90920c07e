"""Datasets with many failed shards: a record carries the errors of the first ERRORS_SHOWN failed shards and counts
them all; the planner publishes nothing for a dataset that is final."""

from __future__ import annotations

import random
import uuid

import pytest
from isolated_stacks import api_on, isolated, queued_tasks
from service_stack import Stack
from test_service_plumbing import FakeSession, make_ctx, new_dataset

from seasynth.service import __version__
from seasynth.service.queues import TASK_PLAN, TASK_SHARD, shard_queue
from seasynth.service.records.store import ERRORS_SHOWN
from seasynth.service.records.types import FAILED


def test_a_record_carries_the_errors_of_the_first_failed_shards_and_counts_them_all(infra: Stack):
    with isolated(infra, 10) as (_, services):
        records = services.records
        ds = new_dataset(records, frames=1000, shard_size=1, dataset_id=uuid.uuid4().hex)
        failed = random.Random(3).sample(range(1000), 700)
        for i in failed:  # in no particular order
            records.fail(ds, i, f"shard {i}: GL context lost")
        first = sorted(failed)[:ERRORS_SHOWN]
        records.fail(ds, first[0], "failed again")  # counted once; the shard's last error is shown
        want = {i: f"shard {i}: GL context lost" for i in first} | {first[0]: "failed again"}
        rec = records.get(ds)
        assert (rec.shards_failed, rec.errors) == (700, want)
        # What a record holds stays bounded: ERRORS_SHOWN shard indices, whatever the failures.
        assert records._r.zcard(records._key(ds, "shown")) == ERRORS_SHOWN
        with api_on(services) as client:
            got = client.get(f"/datasets/{ds}").json()
        assert got["shards_failed"] == 700
        assert got["errors"] == [{"shard": i, "error": want[i]} for i in first]


def test_a_record_written_before_the_bound_shows_its_first_failed_shards(infra: Stack):
    """Failed shards recorded without the index of shown ones (an older version) are indexed on the first read."""
    with isolated(infra, 10) as (_, services):
        records = services.records
        ds = new_dataset(records, frames=50, shard_size=1, dataset_id=uuid.uuid4().hex)
        records._r.sadd(records._key(ds, "failed"), *range(10, 50))
        records._r.hset(records._key(ds, "errors"), mapping={i: f"error {i}" for i in range(5, 50)})
        rec = records.get(ds)
        assert (rec.shards_failed, rec.errors) == (40, {i: f"error {i}" for i in range(10, 10 + ERRORS_SHOWN)})
        records.fail(ds, 3, "error 3")  # a lower index takes its place among the first
        assert records.get(ds).errors == {3: "error 3", **{i: f"error {i}" for i in range(10, 9 + ERRORS_SHOWN)}}


@pytest.mark.parametrize("final", ["failed", "succeeded", "cancelled"])
def test_the_planner_publishes_nothing_for_a_final_dataset(infra: Stack, tmp_path, final):
    from seasynth.worker.queue.app import create_app

    with isolated(infra, 10) as (_, services):
        records = services.records
        plan = create_app(services.settings).tasks[TASK_PLAN]
        plan.resources._ctx = make_ctx(infra, records, tmp_path, FakeSession())  # no GL: the planner renders nothing
        queue = shard_queue(__version__)
        ds = new_dataset(records, frames=6, shard_size=2, dataset_id=uuid.uuid4().hex)
        # Live, it publishes every shard.
        assert plan(ds, 0) == 3
        assert queued_tasks(services.raw_redis, queue) == [(TASK_SHARD, [ds, i, False]) for i in range(3)]
        services.raw_redis.delete(queue)
        if final == FAILED:
            for i in range(3):
                records.fail(ds, i, "attempts used up")
        records.finish(ds, final, 0.0)
        assert plan(ds, 0) == 0 and plan(ds, 0, True) == 0
        assert queued_tasks(services.raw_redis, queue) == []
