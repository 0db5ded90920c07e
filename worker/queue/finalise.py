"""A dataset's end: once every shard is committed or failed, its final state decided (atomically against a cancel)
and manifest.json written, exactly once."""

from __future__ import annotations

import logging
import time

from seasynth.service.manifest import build_manifest, manifest_bytes
from seasynth.service.records.types import FAILED, SUCCEEDED, TERMINAL
from seasynth.service.shards import manifest_key
from seasynth.worker.queue.context import ShardContext

log = logging.getLogger(__name__)

FINALISE_LOCK_S = 300


def fail_shard(ctx: ShardContext, dataset_id: str, index: int, message: str) -> None:
    ctx.records.fail(dataset_id, index, message)
    finalise_or_defer(ctx, dataset_id)


def finalise_or_defer(ctx: ShardContext, dataset_id: str) -> None:
    """maybe_finalise after a shard's outcome is recorded. The outcome stands if finalising fails (e.g. the bucket
    is unreachable): the dataset's next status read or `seasynth reconcile` has a worker finalise it."""
    try:
        maybe_finalise(ctx, dataset_id)
    except Exception:
        log.exception("dataset %s: finalising failed; left to the reconciler", dataset_id)


def maybe_finalise(ctx: ShardContext, dataset_id: str) -> bool:
    """When every shard is committed or failed, decide the final state and write manifest.json, exactly once.

    The state is decided first, atomically against a cancel (records.cancel moves only a live dataset): a cancel
    that comes first leaves the dataset cancelled and no manifest is written; one that comes after finds the
    dataset finished (the API answers 409). manifest.json follows the decision; if writing it fails, the dataset
    stays in the set of pending manifests and the next reconcile (the periodic reconciler nudges one) writes it.
    Returns True when this call wrote the manifest.
    """
    rec = ctx.records.get(dataset_id)
    if rec.shards_done + rec.shards_failed < rec.shards_total:
        return False
    if rec.state in TERMINAL and not ctx.records.manifest_pending(dataset_id):
        return False
    if not ctx.records.claim_finalise(dataset_id, FINALISE_LOCK_S):
        return False
    try:
        if rec.state not in TERMINAL:
            state = SUCCEEDED if rec.shards_failed == 0 else FAILED
            decided = ctx.records.decide(dataset_id, state, time.time())
            if decided != state:  # cancelled (or finished by another finaliser) before we decided
                return False
        elif not ctx.records.manifest_pending(dataset_id):  # another finaliser wrote it meanwhile
            return False
        rec = ctx.records.get(dataset_id)  # as decided: state and finished_at
        key = manifest_key(dataset_id)
        if not ctx.records.purge_started(dataset_id):
            ctx.store.put_bytes(key, manifest_bytes(build_manifest(rec, ctx.records.commits(dataset_id))),
                                "application/json")
        # A purge that began while we wrote, or before a finaliser that died between its write and this check.
        if ctx.records.purge_started(dataset_id):
            ctx.store.delete(key)
        ctx.records.drop_pending_manifest(dataset_id)
    except BaseException:
        ctx.records.release_finalise(dataset_id)
        raise
    log.info("dataset %s %s", dataset_id, rec.state)
    return True
