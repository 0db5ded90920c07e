"""One shard end to end: render its frames, pack a deterministic tar (and its export parts: worker.shard_exports),
upload them atomically, commit, track completion.

Every step is idempotent: keys are deterministic, a shard's tar is a pure function of (spec, frames, renderer),
a committed shard is skipped, and a retry's commit counts once (records.commit). Celery tasks wrap these
functions and map `RetryShard` onto a task retry.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Protocol

from service import __version__
from service.errors import AssetError, NotFound, Unreachable
from service.manifest import build_manifest, manifest_bytes, pending_manifests_key
from service.records import CANCELLED, FAILED, SUCCEEDED, TERMINAL, Records, ShardCommit
from service.settings import Settings
from service.shards import (
    FRAME_PARTS,
    Shard,
    asset_info_key,
    asset_key,
    commit_key,
    commit_prefix,
    frame_file,
    manifest_key,
    shard_at,
    shard_key,
)
from service.spec import DatasetSpec, parse_spec
from service.storage import ObjectStore
from worker.export.parts import kitti_names, parts_render_spec
from worker.packing import pack_tar
from worker.shard_exports import keep_frame, pack_parts, part_keys, upload_parts

log = logging.getLogger(__name__)

FINALISE_LOCK_S = 300


class FrameSource(Protocol):
    """What a shard needs of the pipeline's RenderSession."""

    renderer_name: str

    def frame_files(self, spec: DatasetSpec, index: int) -> dict[str, bytes]: ...


class Outcome(str, Enum):
    COMMITTED = "committed"
    ALREADY_COMMITTED = "already-committed"
    RUNNING_ELSEWHERE = "running-elsewhere"  # a reconciler's copy found the shard running within its lease
    CANCELLED = "cancelled"
    MISSING = "missing"  # no such dataset (expired or never created)
    FAILED = "failed"
    DEFERRED = "deferred"  # pinned to another renderer: handed back for a worker that has it


class RetryShard(Exception):
    """The attempt failed with attempts left: run the shard again after `countdown` seconds."""

    def __init__(self, message: str, countdown: float):
        super().__init__(message)
        self.countdown = countdown


class WrongVersion(Exception):
    """A shard of a dataset pinned to another code version reached this worker; it must go back untouched."""

    def __init__(self, version: str):
        super().__init__(f"dataset is pinned to code version {version}, this worker runs {__version__}")
        self.version = version


class WrongRenderer(Exception):
    """A shard or frame of a dataset pinned to another GL renderer reached this worker; it must go back untouched."""

    def __init__(self, dataset_id: str, pinned: str, ours: str):
        super().__init__(f"dataset {dataset_id} is rendered with {pinned!r}; this worker runs {ours!r}")
        self.pinned = pinned


@dataclass
class ShardContext:
    """Per-process resources a shard or frame task uses; built in each pool process after the fork."""

    settings: Settings
    records: Records
    raw_redis: Any  # a redis client with decode_responses=False, for frame answers
    store: ObjectStore
    session: FrameSource
    host: str = field(default_factory=socket.gethostname)
    code_version: str = __version__
    # How long a dataset waits for a live shard worker with its pinned renderer before it fails; None: the
    # settings' renderer_wait_s where it exists (SEASYNTH_RENDERER_WAIT_S), else the stall timeout.
    renderer_wait_s: float | None = None
    _specs: dict[str, DatasetSpec] = field(default_factory=dict)

    def spec(self, dataset_id: str, spec_json: dict[str, Any]) -> DatasetSpec:
        """The dataset's spec, parsed once per process (a few recent datasets are kept)."""
        if dataset_id not in self._specs:
            if len(self._specs) >= 16:
                self._specs.pop(next(iter(self._specs)))
            self._specs[dataset_id] = parse_spec(spec_json, source=f"dataset {dataset_id}")
        return self._specs[dataset_id]


class _Cancelled(Exception):
    pass


def shard_files(
    session: FrameSource, spec: DatasetSpec, shard: Shard, cancelled: Callable[[], bool], keep: Path | None = None
) -> Iterator[tuple[str, bytes]]:
    """A shard's members in order: frame by frame, each frame's files by name.

    keep: a folder that also gets each frame's files, for the shard's export parts; the frames are then rendered
    with what the parts need (worker.export.parts.parts_render_spec), and files only they need stay out of the tar.
    """
    render = spec if keep is None else parts_render_spec(spec)
    for index in shard.frames:
        if cancelled():
            raise _Cancelled
        files = session.frame_files(render, index)
        if keep is not None:
            keep_frame(keep, files)
        for name in kitti_names(spec, render, index, list(files)):
            yield name, files[name]


# --- the shard task body


def run_shard(ctx: ShardContext, dataset_id: str, index: int, sweep: bool = False) -> Outcome:
    """Render, pack, upload and commit one shard unless it is committed, cancelled or out of attempts.

    Every failure counts as an attempt, also one before the attempt started (Redis or the bucket briefly
    unreachable): RetryShard while attempts are left, then the shard is marked failed. WrongVersion and
    WrongRenderer send the shard back without counting. `sweep`: this is a reconciler's copy, which leaves a shard
    running within its lease to that execution.
    """
    try:
        early = _before_attempt(ctx, dataset_id, index, sweep)
    except (WrongVersion, WrongRenderer):
        raise
    except Exception as err:
        log.exception("shard %s of dataset %s failed before its attempt started", index, dataset_id)
        return _count_failed_execution(ctx, dataset_id, index, err)
    if early is not None:
        return early

    running = {"pid": os.getpid(), "host": ctx.host, "since": time.time()}
    attempt = ctx.records.start_attempt(dataset_id, index, ctx.settings.max_attempts, running)
    if attempt == -2:  # the record went between the two reads (Redis lost its data): nothing to count against
        log.warning("shard %s of dataset %s: the record is gone, dropped", index, dataset_id)
        return Outcome.MISSING
    if attempt < 0:
        last = ctx.records.last_error(dataset_id, index) or "the worker was lost while rendering it"
        fail_shard(ctx, dataset_id, index, f"gave up after {ctx.settings.max_attempts} attempts; last: {last}")
        return Outcome.FAILED
    try:
        outcome = _attempt(ctx, dataset_id, index, attempt)
    except Exception:
        ctx.records.end_attempt(dataset_id, index)
        raise
    except BaseException:
        # SystemExit mid-frame (Celery terminating the task, whose pool process is to exit, e.g. on a broker
        # connection loss) must reach the process. Were an unreachable Redis here to replace it with an Exception,
        # the process would live on with its GL state cut mid-draw, and the next frame it rendered would differ.
        with contextlib.suppress(Exception):
            ctx.records.end_attempt(dataset_id, index)
        raise
    ctx.records.end_attempt(dataset_id, index)
    return outcome


def _attempt(ctx: ShardContext, dataset_id: str, index: int, attempt: int) -> Outcome:
    """The body of a counted attempt: adopt a marker Redis missed, or render and commit."""
    try:
        _renderer_found(ctx, dataset_id, index)
        if _adopt_marker(ctx, dataset_id, index):
            finalise_or_defer(ctx, dataset_id)
            return Outcome.ALREADY_COMMITTED
        return _render_and_commit(ctx, dataset_id, index)
    except _Cancelled:
        return Outcome.CANCELLED
    except Exception as err:
        log.exception("shard %s of dataset %s failed", index, dataset_id)
        return _attempt_failed(ctx, dataset_id, index, attempt, err)


def _before_attempt(ctx: ShardContext, dataset_id: str, index: int, sweep: bool) -> Outcome | None:
    """Why this execution need not render (an Outcome), or None; pins the dataset's renderer on first use."""
    try:
        rec = ctx.records.get(dataset_id)
    except NotFound:
        log.warning("shard %s of dataset %s: no such dataset, dropped", index, dataset_id)
        return Outcome.MISSING
    if rec.code_version != ctx.code_version:
        raise WrongVersion(rec.code_version)
    if rec.state == CANCELLED:
        # An earlier execution may have written after a purge listed the prefix, then died before taking its
        # objects back: take them back now (only a shard that ran can have written any).
        if ctx.records.purge_started(dataset_id) and ctx.records.attempts(dataset_id, index):
            _take_back(ctx, dataset_id, index)
        return Outcome.CANCELLED
    if ctx.records.is_committed(dataset_id, index):
        finalise_or_defer(ctx, dataset_id)
        return Outcome.ALREADY_COMMITTED
    if ctx.records.is_failed(dataset_id, index):
        finalise_or_defer(ctx, dataset_id)
        return Outcome.FAILED
    ours = ctx.session.renderer_name
    pinned = ctx.records.set_renderer(dataset_id, ours)  # first writer wins, atomically
    if pinned != ours:
        raise WrongRenderer(dataset_id, pinned, ours)
    if sweep and index in ctx.records.live_running(dataset_id, time.time(), ctx.settings.running_lease_s):
        return Outcome.RUNNING_ELSEWHERE
    return None


def _attempt_failed(ctx: ShardContext, dataset_id: str, index: int, attempt: int, err: Exception) -> Outcome:
    """Record a counted attempt's error; RetryShard while attempts are left, else mark the shard failed.

    An attempt that failed because the bucket was unreachable (Unreachable: refused, reset, timed out, 5xx) is
    given back instead: an outage says nothing of the shard, and a bucket away for longer than three quick retries
    (about 10 s) would otherwise fail every shard in flight. Its retries back off up to retry_backoff_max_s, for as
    long as the outage lasts.
    """
    msg = f"attempt {attempt}: {type(err).__name__}: {err}"
    if isinstance(err, Unreachable):
        outages = ctx.records.refund_attempt(dataset_id, index)
        ctx.records.record_error(dataset_id, index, f"{msg} (an outage: retried without using up an attempt)")
        raise RetryShard(msg, countdown=min(2.0 ** (outages - 1), ctx.settings.retry_backoff_max_s)) from err
    ctx.records.record_error(dataset_id, index, msg)
    if attempt >= ctx.settings.max_attempts:
        fail_shard(ctx, dataset_id, index, f"gave up after {attempt} attempts; last: {msg}")
        return Outcome.FAILED
    # The delay stays far below the visibility timeout (a longer ETA would be redelivered meanwhile).
    raise RetryShard(msg, countdown=min(2.0 ** (attempt - 1), ctx.settings.retry_backoff_max_s)) from err


def _count_failed_execution(ctx: ShardContext, dataset_id: str, index: int, err: Exception) -> Outcome:
    """An execution that failed before its attempt was counted: count it now, then retry or give up."""
    running = {"pid": os.getpid(), "host": ctx.host, "since": time.time()}
    attempt = ctx.records.start_attempt(dataset_id, index, ctx.settings.max_attempts, running)
    ctx.records.end_attempt(dataset_id, index)
    if attempt < 0:
        last = f"{type(err).__name__}: {err}"
        fail_shard(ctx, dataset_id, index, f"gave up after {ctx.settings.max_attempts} attempts; last: {last}")
        return Outcome.FAILED
    return _attempt_failed(ctx, dataset_id, index, attempt, err)


def _render_and_commit(ctx: ShardContext, dataset_id: str, index: int) -> Outcome:
    rec = ctx.records.get(dataset_id)
    shard = shard_at(rec.frames_total, rec.shard_size, index)
    spec = ctx.spec(dataset_id, rec.spec)
    renderer = ctx.session.renderer_name  # pinned for the dataset before the attempt started
    compression = ctx.settings.shard_compression
    key = shard_key(dataset_id, shard.index, compression)
    cancelled = lambda: ctx.records.state(dataset_id) == CANCELLED  # noqa: E731
    with tempfile.TemporaryDirectory(prefix="seasynth-shard-") as work:
        tar, keep = Path(work) / "shard.tar", (Path(work) / "frames" if spec.outputs.exports else None)
        with open(tar, "wb") as f:
            sha, size = pack_tar(shard_files(ctx.session, spec, shard, cancelled, keep), f, compression)
        packed = [] if keep is None else pack_parts(spec, shard, keep, Path(work), rec.code_version)
        if cancelled():
            return Outcome.CANCELLED
        # The tar and the export parts become visible whole (one PUT or a completed multipart upload each), then
        # the marker commits them.
        ctx.store.put_file(key, tar, "application/gzip" if compression == "gz" else "application/x-tar")
        exports = upload_parts(ctx.store, dataset_id, shard.index, packed)
    commit = ShardCommit(
        index=shard.index,
        key=key,
        first_frame=shard.first_frame,
        frame_count=shard.frame_count,
        sha256=sha,
        bytes=size,
        code_version=ctx.code_version,
        renderer=renderer,
        exports=exports,
    )
    ctx.store.put_bytes(commit_key(dataset_id, shard.index), commit.to_json().encode(), "application/json")
    ctx.records.commit(dataset_id, commit)
    # Checked after both writes: a purge that began before this answer may have listed the prefix without them.
    if ctx.records.purge_started(dataset_id):
        _take_back(ctx, dataset_id, shard.index)
        return Outcome.CANCELLED
    log.info("dataset %s shard %s committed: frames %s..%s", dataset_id, shard.index, shard.first_frame,
             shard.first_frame + shard.frame_count - 1)
    finalise_or_defer(ctx, dataset_id)
    return Outcome.COMMITTED


def _take_back(ctx: ShardContext, dataset_id: str, index: int) -> None:
    """Delete what an execution of shard `index` may have written (its tar, in either compression, its export
    parts and its commit marker) once the dataset's purge has begun."""
    written = (shard_key(dataset_id, index, "none"), shard_key(dataset_id, index, "gz"), *part_keys(dataset_id, index),
               commit_key(dataset_id, index))
    for key in written:
        ctx.store.delete(key)


def _adopt_marker(ctx: ShardContext, dataset_id: str, index: int) -> bool:
    """A commit marker in storage that Redis does not know (e.g. Redis lost it): count it now."""
    try:
        data = ctx.store.get_bytes(commit_key(dataset_id, index))
    except NotFound:
        return False
    ctx.records.commit(dataset_id, ShardCommit.from_json(data))
    return True


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


# Decides a complete dataset's final state in one step, unless it is final already (a cancel came first): the
# state, finished_at, and the dataset's entry in the set of manifests still to write. Returns the state after.
_DECIDE = """
local s = redis.call('HGET', KEYS[1], 'state')
if not s then return nil end
if s == 'queued' or s == 'running' then
  redis.call('HSET', KEYS[1], 'state', ARGV[1], 'finished_at', ARGV[2])
  redis.call('SADD', KEYS[2], ARGV[3])
  return ARGV[1]
end
return s
"""


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
    pending = pending_manifests_key(ctx.records.p)
    if rec.state in TERMINAL and not ctx.records.r.sismember(pending, dataset_id):
        return False
    if not ctx.records.claim_finalise(dataset_id, FINALISE_LOCK_S):
        return False
    try:
        if rec.state not in TERMINAL:
            state = SUCCEEDED if rec.shards_failed == 0 else FAILED
            decided = _script(ctx, _DECIDE)(keys=[ctx.records._k(dataset_id), pending],
                                             args=[state, repr(time.time()), dataset_id])
            if decided != state:  # cancelled (or finished by another finaliser) before we decided
                return False
        elif not ctx.records.r.sismember(pending, dataset_id):  # another finaliser wrote it meanwhile
            return False
        rec = ctx.records.get(dataset_id)  # as decided: state and finished_at
        key = manifest_key(dataset_id)
        if not ctx.records.purge_started(dataset_id):
            ctx.store.put_bytes(key, manifest_bytes(build_manifest(rec, ctx.records.commits(dataset_id))),
                                "application/json")
        # A purge that began while we wrote, or before a finaliser that died between its write and this check.
        if ctx.records.purge_started(dataset_id):
            ctx.store.delete(key)
        ctx.records.r.srem(pending, dataset_id)
    except BaseException:
        ctx.records.release_finalise(dataset_id)
        raise
    log.info("dataset %s %s", dataset_id, rec.state)
    return True


def reconcile(ctx: ShardContext, dataset_id: str) -> list[int]:
    """Adopt commit markers Redis missed, finalise if complete (or write a manifest whose write failed); return
    the shards to publish again: neither committed, nor failed, nor running within their lease, nor handed back
    recently by a worker of another renderer (that message is still going round)."""
    for info in ctx.store.list(commit_prefix(dataset_id)):
        commit = ShardCommit.from_json(ctx.store.get_bytes(info.key))
        ctx.records.commit(dataset_id, commit)
    maybe_finalise(ctx, dataset_id)
    rec = ctx.records.get(dataset_id)
    if rec.state in TERMINAL:
        return []
    return sweepable(ctx, dataset_id, list(range(rec.shards_total)), time.time())


def sweepable(ctx: ShardContext, dataset_id: str, indices: list[int], now: float) -> list[int]:
    """Of `indices`, the shards a sweep may publish again: pending (records.pending) and not handed back by a
    worker of another renderer within the stall timeout, since such a shard's message is still in circulation
    (publishing another copy would only multiply the messages going round)."""
    pending = ctx.records.pending(dataset_id, indices, now, ctx.settings.running_lease_s)
    if not pending:
        return []
    handed_back = ctx.records.r.hmget(_deferred_key(ctx, dataset_id), pending)
    stall = ctx.settings.stall_s
    return [i for i, t in zip(pending, handed_back) if t is None or now - float(t) >= stall]


# --- renderer pinning: hand-backs, which renderers have live shard workers, giving up

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


def _deferred_key(ctx: ShardContext, dataset_id: str) -> str:
    """HASH shard index -> last time a worker of another renderer handed it back (epoch s)."""
    return ctx.records._k(dataset_id, "deferred")


def renderer_wait_s(ctx: ShardContext) -> float:
    wait = getattr(ctx.settings, "renderer_wait_s", None)
    if wait is None:
        wait = ctx.renderer_wait_s
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
    got = _script(ctx, _HAND_BACK)(keys=[ctx.records._k(dataset_id), _deferred_key(ctx, dataset_id)],
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
    _script(ctx, _SET_IF_EXISTS)(keys=[ctx.records._k(dataset_id)], args=["notice", notice])
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
    _script(ctx, _SET_IF_EXISTS)(keys=[ctx.records._k(dataset_id)], args=["notice", message])
    finalise_or_defer(ctx, dataset_id)
    return failed


def _script(ctx: ShardContext, source: str):
    """A Lua script on the records' Redis, run by its sha (registering computes it locally; no round trip)."""
    return ctx.records.r.register_script(source)


def _renderer_found(ctx: ShardContext, dataset_id: str, index: int) -> None:
    _script(ctx, _FOUND)(keys=[ctx.records._k(dataset_id), _deferred_key(ctx, dataset_id)], args=[index])


# --- single frames


def render_frame(ctx: ShardContext, dataset_id: str, index: int, part: str) -> tuple[dict[str, Any], bytes]:
    """One file of one frame, re-rendered from (spec, seed, index): (header, body) for the waiting API."""
    rec = ctx.records.get(dataset_id)
    if rec.code_version != ctx.code_version:
        raise WrongVersion(rec.code_version)
    ours = ctx.session.renderer_name
    if rec.renderer is not None and rec.renderer != ours:  # its shards' bytes come from that renderer only
        raise WrongRenderer(dataset_id, rec.renderer, ours)
    if not 0 <= index < rec.frames_total or part not in FRAME_PARTS:
        raise NotFound(f"dataset {dataset_id} has no frame {index} part {part}")
    files = ctx.session.frame_files(ctx.spec(dataset_id, rec.spec), index)
    name = frame_file(part, index)
    if name not in files:
        raise NotFound(f"frame {index} of dataset {dataset_id} has no {name} (is that output switched on?)")
    return {"ok": True, "name": name, "renderer": ctx.session.renderer_name}, files[name]


# --- uploaded assets


class AssetCache:
    """Maps an uploaded asset id to a local file: downloaded once per process, verified by its sha256."""

    def __init__(self, store: ObjectStore, folder: Path):
        self.store = store
        self.folder = Path(folder)

    def __call__(self, asset_id: str) -> Path:
        info = json.loads(self.store.get_bytes(asset_info_key(asset_id)))
        suffix = Path(info.get("filename", "")).suffix.lower()
        dest = self.folder / f"{asset_id}{suffix}"
        if dest.is_file():
            return dest
        self.folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".part-")
        os.close(fd)
        try:
            self.store.download(asset_key(asset_id), Path(tmp))
            digest = hashlib.sha256(Path(tmp).read_bytes()).hexdigest()
            if digest != asset_id:
                raise AssetError(f"asset {asset_id}: downloaded bytes have sha256 {digest}")
            os.replace(tmp, dest)
        finally:
            Path(tmp).unlink(missing_ok=True)
        return dest
