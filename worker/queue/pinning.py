"""Renderer pinning: a dataset's shards are rendered by one GL renderer (the first to take one). Which renderers have
live shard workers, shards handed back by workers of another renderer, and giving up when none comes."""

from __future__ import annotations

import time

from seasynth.worker.queue.context import Outcome, ShardContext, WrongRenderer
from seasynth.worker.queue.finalise import finalise_or_defer

HEARTBEAT_S = 15  # a shard worker's render process notes its renderer this often
RENDERER_LIVE_S = 60  # a renderer not noted for this long has no live shard worker


def renderer_live(ctx: ShardContext, renderer: str, now: float) -> bool:
    """Whether a shard worker of this code version with `renderer` has noted itself within RENDERER_LIVE_S."""
    seen = ctx.records.renderer_seen(ctx.code_version, renderer)
    return seen is not None and now - seen < RENDERER_LIVE_S


def renderer_wait_s(ctx: ShardContext) -> float:
    """How long a dataset waits for a live shard worker with its pinned renderer: settings.renderer_wait_s
    (SEASYNTH_RENDERER_WAIT_S), else the stall timeout."""
    wait = ctx.settings.renderer_wait_s
    return float(ctx.settings.stall_s if wait is None else wait)


def defer_to_renderer(ctx: ShardContext, dataset_id: str, index: int, wrong: WrongRenderer,
                      now: float | None = None) -> Outcome:
    """A worker of another renderer got shard `index`: DEFERRED (hand it back), or FAILED once no shard worker
    with the pinned renderer has been alive for renderer_wait_s.

    Every hand-back is counted and shown in the record's `notice`; the dataset counts as active (no sweep
    republishes it), and the shard is marked handed back so that a forced sweep leaves it alone too. Giving up
    fails every pending shard with an error naming the missing renderer, and finalises the dataset (failed).
    """
    now = time.time() if now is None else now
    ours = ctx.session.renderer_name
    live = renderer_live(ctx, wrong.pinned, now)
    got = ctx.records.hand_back(dataset_id, index, now, live)
    if got is None:
        return Outcome.MISSING
    handbacks, since = got
    wait = renderer_wait_s(ctx)
    if since is not None and now - since >= wait:
        message = (f"no shard worker with renderer {wrong.pinned!r}, which this dataset was started with, ran for "
                   f"{now - since:.0f} s (the wait is {wait:.0f} s, SEASYNTH_RENDERER_WAIT_S); workers running "
                   f"{ours!r} handed its shards back {handbacks} times. Run a worker with that renderer and create "
                   "the dataset again")
        give_up_pending(ctx, dataset_id, message, now)
        return Outcome.FAILED
    if live:
        state = "one is running (all its processes busy)"
    else:
        left = wait - (now - since)
        state = f"none has run for {now - since:.0f} s; the dataset fails if none comes within {left:.0f} s"
    notice = (f"waiting for a shard worker with renderer {wrong.pinned!r}: {state}; {handbacks} hand-backs by "
              f"workers running {ours!r}")
    ctx.records.set_notice(dataset_id, notice)
    return Outcome.DEFERRED


def give_up_pending(ctx: ShardContext, dataset_id: str, message: str, now: float) -> int:
    """Fail every shard of the dataset that is neither committed, nor failed, nor running; then finalise.
    Returns how many shards were failed."""
    rec = ctx.records.get(dataset_id)
    failed = 0
    for first in range(0, rec.shards_total, ctx.settings.plan_batch):
        batch = list(range(first, min(first + ctx.settings.plan_batch, rec.shards_total)))
        for i in ctx.records.pending(dataset_id, batch, now, ctx.settings.running_lease_s):
            ctx.records.fail(dataset_id, i, message)
            failed += 1
    ctx.records.set_notice(dataset_id, message)
    finalise_or_defer(ctx, dataset_id)
    return failed
