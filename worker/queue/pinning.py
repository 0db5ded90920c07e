"""Renderer pinning: a dataset's shards are rendered by one GL renderer (the first to take one). Which renderers have
live shard workers, shards handed back by workers of another renderer, and giving up when none comes."""

from __future__ import annotations

import time

from seasynth.worker.queue.finalise import finalise_or_defer
from seasynth.worker.queue.context import Outcome, ShardContext, WrongRenderer, script

HEARTBEAT_S = 15  # a shard worker's render process notes its renderer this often
RENDERER_LIVE_S = 60  # a renderer not noted for this long has no live shard worker


def renderers_key(prefix: str, version: str) -> str:
    """ZSET renderer name -> last time a render process of a shard worker of `version` noted it (epoch s)."""
    return f"{prefix}:renderers:{version}"


def note_renderer(redis, prefix: str, version: str, renderer: str, now: float) -> None:
    redis.zadd(renderers_key(prefix, version), {renderer: now})


def renderer_live(ctx: ShardContext, renderer: str, now: float) -> bool:
    """Whether a shard worker of this code version with `renderer` has noted itself within RENDERER_LIVE_S."""
    seen = ctx.records.r.zscore(renderers_key(ctx.records.p, ctx.code_version), renderer)
    return seen is not None and now - float(seen) < RENDERER_LIVE_S


def deferred_key(ctx: ShardContext, dataset_id: str) -> str:
    """HASH shard index -> last time a worker of another renderer handed it back (epoch s)."""
    return ctx.records._k(dataset_id, "deferred")


def renderer_wait_s(ctx: ShardContext) -> float:
    """How long a dataset waits for a live shard worker with its pinned renderer: settings.renderer_wait_s
    (SEASYNTH_RENDERER_WAIT_S), else the stall timeout."""
    wait = ctx.settings.renderer_wait_s
    return float(ctx.settings.stall_s if wait is None else wait)


# Counts a hand-back and keeps the dataset from looking stalled (a sweep would publish the shard again while its
# message goes round). waiting_since: the first hand-back since a live worker of the pinned renderer was last
# seen. Returns {hand-backs, waiting_since or ''}, nil for no such dataset.
_HAND_BACK = """
if redis.call('EXISTS', KEYS[1]) == 0 then return nil end
local n = redis.call('HINCRBY', KEYS[1], 'handbacks', 1)
redis.call('HSET', KEYS[1], 'touched_at', ARGV[2])
redis.call('HSET', KEYS[2], ARGV[1], ARGV[2])
if ARGV[3] == '1' then
  redis.call('HDEL', KEYS[1], 'waiting_since')
  return {n, ''}
end
redis.call('HSETNX', KEYS[1], 'waiting_since', ARGV[2])
return {n, redis.call('HGET', KEYS[1], 'waiting_since')}
"""

# Sets fields of an existing record only (a late writer never recreates a discarded dataset's hash).
_SET_IF_EXISTS = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
redis.call('HSET', KEYS[1], unpack(ARGV))
return 1
"""

# A worker of the pinned renderer took a shard: nothing is waiting for one any more.
_FOUND = """
redis.call('HDEL', KEYS[2], ARGV[1])
if redis.call('HEXISTS', KEYS[1], 'notice') == 1 then redis.call('HDEL', KEYS[1], 'notice', 'waiting_since') end
return 0
"""


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
    got = script(ctx, _HAND_BACK)(keys=[ctx.records._k(dataset_id), deferred_key(ctx, dataset_id)],
                                  args=[index, repr(now), "1" if live else "0"])
    if got is None:
        return Outcome.MISSING
    handbacks, since = int(got[0]), (float(got[1]) if got[1] else None)
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
    script(ctx, _SET_IF_EXISTS)(keys=[ctx.records._k(dataset_id)], args=["notice", notice])
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
    script(ctx, _SET_IF_EXISTS)(keys=[ctx.records._k(dataset_id)], args=["notice", message])
    finalise_or_defer(ctx, dataset_id)
    return failed


def renderer_found(ctx: ShardContext, dataset_id: str, index: int) -> None:
    script(ctx, _FOUND)(keys=[ctx.records._k(dataset_id), deferred_key(ctx, dataset_id)], args=[index])
