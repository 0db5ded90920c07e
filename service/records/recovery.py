"""Recovery from a Redis restart: each dataset's creation record is kept in the bucket too, so a Redis that lost its
data (persistence off, a lost volume) gets the dataset back from what the bucket holds instead of forgetting it; a
Redis that restarted with its data has the executions it cut off republished at once.

Bucket keys (S = the Redis key prefix and database, so deployments sharing a bucket keep apart):
  records/S/{id}.json        the creation record (spec, seed, code version, sizes, created_at), written before the
                             dataset is published, deleted first by a purge
  records/S/{id}.cancelled   written before a cancel, so a restored dataset stays cancelled
Redis key:
  P:redis:run               the run_id of the Redis process the last recovery check saw; written only after the
                             check's work is done, so a reconciler killed mid-way leaves it to the next one
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

from seasynth.service.errors import NotFound
from seasynth.service.records.store import Records
from seasynth.service.records.types import FAILED, SUCCEEDED, ShardCommit
from seasynth.service.shards import commit_prefix, manifest_key
from seasynth.service.storage import ObjectStore


def scope(records: Records) -> str:
    """This deployment's part of the bucket: its key prefix and Redis database."""
    return f"records/{records.namespace()}/"


def record_key(records: Records, dataset_id: str) -> str:
    return f"{scope(records)}{dataset_id}.json"


def cancelled_key(records: Records, dataset_id: str) -> str:
    return f"{scope(records)}{dataset_id}.cancelled"


def save_record(records: Records, store: ObjectStore, dataset_id: str, fields: dict[str, Any]) -> None:
    """Keep a new dataset's creation fields (Records.create's keywords and its id and spec) in the bucket."""
    store.put_bytes(record_key(records, dataset_id), json.dumps(fields, sort_keys=True).encode(), "application/json")


def forget(records: Records, store: ObjectStore, dataset_id: str) -> None:
    """Delete a purged dataset's bucket records, so nothing restores it."""
    store.delete(record_key(records, dataset_id))
    store.delete(cancelled_key(records, dataset_id))


def restore(records: Records, store: ObjectStore, dataset_id: str, now: float) -> bool:
    """Recreate the Redis record of a dataset the bucket has a record of: its committed shards from their markers,
    its final state from its manifest (or cancelled), else live and due a sweep at once. False when the bucket has
    no record of it (never created here, or purged). The record says restored_at: attempts, errors and timings
    from before are lost."""
    try:
        fields = json.loads(store.get_bytes(record_key(records, dataset_id)))
    except NotFound:
        return False
    if not records.restore(dataset_id, fields["spec"], seed=fields["seed"], code_version=fields["code_version"],
                           frames=fields["frames"], shard_size=fields["shard_size"], shards=fields["shards"],
                           created_at=fields["created_at"], now=now):
        return True  # another restorer won, or Redis has it again
    for info in store.list(commit_prefix(dataset_id)):  # not touched: the restored record stays due a sweep
        records.commit(dataset_id, ShardCommit.from_json(store.get_bytes(info.key)), touch=False)
    if store.head(cancelled_key(records, dataset_id)) is not None:
        records.cancel(dataset_id, now)
        return True
    try:
        state = json.loads(store.get_bytes(manifest_key(dataset_id)))["state"]
    except NotFound:
        return True
    if state in (SUCCEEDED, FAILED):
        records.finish(dataset_id, state, now)
    return True


@dataclass(frozen=True)
class RedisCheck:
    """What a recovery check found and did."""

    restarted: bool  # Redis is another process than at the last check
    lost_data: bool  # ... and came back without its data (or is new)
    restored: list[str]  # datasets recreated from the bucket
    cut_off: list[str]  # live datasets whose executions the restart cut off (their running entries were cleared)


def check_redis(records: Records, store: ObjectStore, now: float | None = None) -> RedisCheck:
    """Notice a Redis restart since the last check and recover from it; the reconciler runs this each round.

    Without its data: every dataset with a bucket record and no Redis record is restored (restore). With its data:
    the shard executions running when Redis went away were terminated by their workers (Celery cancels running
    tasks on a broker connection loss) and their messages wait in Redis's unacknowledged set for the visibility
    timeout; their running entries are cleared, so that a sweep (the caller forces one of each dataset returned)
    publishes those shards again now instead of after the stall timeout.
    """
    now = time.time() if now is None else now
    run_id, uptime_s = records.redis_run()
    started = now - uptime_s
    seen = records.seen_redis_run()
    if seen == run_id:
        return RedisCheck(False, False, [], [])
    restored, cut_off = [], []
    if seen is None:
        for obj in store.list(scope(records)):
            dataset_id = obj.key[len(scope(records)):].removesuffix(".json")
            if obj.key.endswith(".json") and not records.exists(dataset_id):
                if restore(records, store, dataset_id, now):
                    restored.append(dataset_id)
    else:
        cut_off = _clear_cut_off(records, started)
    records.note_redis_run(run_id)
    return RedisCheck(True, seen is None, restored, cut_off)


def _clear_cut_off(records: Records, started: float) -> list[str]:
    """Clear running entries older than the Redis process (`started`) of every live dataset; returns those
    datasets."""
    out, offset = [], 0
    while True:
        ids, total = records.list_ids(offset, 500)
        for dataset_id in ids:
            if records.state(dataset_id) not in ("queued", "running"):
                continue
            dead = [i for i, who in records.running(dataset_id).items() if float(who.get("since", 0)) < started]
            if dead:
                records.clear_running(dataset_id, dead)
                out.append(dataset_id)
        offset += len(ids)
        if not ids or offset >= total:
            return out

