"""One shard end to end: render its frames, pack a deterministic tar (and its export parts: seasynth.worker.queue.shard_exports),
upload them atomically, commit, track completion (seasynth.worker.queue.finalise); the reconciler's sweep; one frame re-rendered.

Every step is idempotent: keys are deterministic, a shard's tar is a pure function of (spec, frames, renderer),
a committed shard is skipped, and a retry's commit counts once (records.commit). Celery tasks wrap these
functions and map `RetryShard` onto a task retry.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from seasynth.service.errors import NotFound, Unreachable
from seasynth.service.records.types import CANCELLED, TERMINAL, ShardCommit
from seasynth.service.shards import FRAME_PARTS, Shard, commit_key, commit_prefix, frame_file, shard_at, shard_key
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.export.parts import kitti_names, parts_render_spec
from seasynth.worker.queue.context import FrameSource, Outcome, RetryShard, ShardContext, WrongRenderer, WrongVersion
from seasynth.worker.queue.finalise import fail_shard, finalise_or_defer, maybe_finalise
from seasynth.worker.queue.packing import pack_tar
from seasynth.worker.queue.shard_exports import keep_frame, pack_parts, part_keys, upload_parts
from seasynth.worker.scene.sample import INPUT_ERRORS

log = logging.getLogger(__name__)


class _Cancelled(Exception):
    pass


def shard_files(
    session: FrameSource, spec: DatasetSpec, shard: Shard, cancelled: Callable[[], bool], keep: Path | None = None
) -> Iterator[tuple[str, bytes]]:
    """A shard's members in order: frame by frame, each frame's files by name.

    keep: a folder that also gets each frame's files, for the shard's export parts; the frames are then rendered
    with what the parts need (seasynth.worker.export.parts.parts_render_spec), and files only they need stay out of the tar.
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
        if _adopt_marker(ctx, dataset_id, index):  # the last attempt wrote its marker, then died before counting it
            return Outcome.ALREADY_COMMITTED
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
    """The body of a counted attempt: adopt a marker Redis missed, or render and commit.

    The marker is read while the frames render (MarkerLookup): a shard used to wait for that read before its
    first frame, 0.1-0.5 s on an S3 server on loopback answering 24 render processes at once (a 720p shard of 25
    frames takes about 1.8 s). Nothing is uploaded before the read has answered.
    """
    try:
        ctx.records.renderer_found(dataset_id, index)
        return _render_and_commit(ctx, dataset_id, index, MarkerLookup(ctx, dataset_id, index))
    except _Cancelled:
        return Outcome.CANCELLED
    except Exception as err:
        log.exception("shard %s of dataset %s failed", index, dataset_id)
        return _attempt_failed(ctx, dataset_id, index, attempt, err)


class _MarkerAnswered(Exception):
    """The marker read found a marker or failed: the frames rendered meanwhile would be thrown away."""


class MarkerLookup:
    """A shard's commit marker read from storage on a thread of its own while the shard renders.

    `answered` is true once the read found a marker or failed (stop rendering); `result` waits for the read and
    gives the marker (None: there is none) or raises the read's error, as the read itself would have.
    """

    def __init__(self, ctx: ShardContext, dataset_id: str, index: int) -> None:
        self._key = commit_key(dataset_id, index)
        self._data: bytes | None = None
        self._err: BaseException | None = None
        self._done = threading.Event()
        threading.Thread(target=self._read, args=(ctx.store,), name="commit-marker-read", daemon=True).start()

    def _read(self, store) -> None:
        try:
            self._data = store.get_bytes(self._key)
        except NotFound:
            pass
        except BaseException as err:  # handed to the shard's thread by result()
            self._err = err
        finally:
            self._done.set()

    @property
    def answered(self) -> bool:
        return self._done.is_set() and (self._data is not None or self._err is not None)

    def result(self) -> bytes | None:
        self._done.wait()
        if self._err is not None:
            raise self._err
        return self._data


def _adopt_marker(ctx: ShardContext, dataset_id: str, index: int) -> bool:
    """Count the shard from its commit marker in the bucket, if there is one; False if there is none. A bucket that
    cannot be read raises: a shard is never given up while its marker may exist (the task publishes it again)."""
    try:
        found = ctx.store.get_bytes(commit_key(dataset_id, index))
    except NotFound:
        return False
    _count_marker(ctx, dataset_id, found)
    return True


def _count_marker(ctx: ShardContext, dataset_id: str, marker: bytes) -> None:
    """Count a commit marker Redis does not know (Redis lost it, or its writer died first), then finalise if due."""
    ctx.records.commit(dataset_id, ShardCommit.from_json(marker))
    finalise_or_defer(ctx, dataset_id)


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


def _render_and_commit(ctx: ShardContext, dataset_id: str, index: int, marker: MarkerLookup) -> Outcome:
    rec = ctx.records.get(dataset_id)
    shard = shard_at(rec.frames_total, rec.shard_size, index)
    spec = ctx.spec(dataset_id, rec.spec)
    renderer = ctx.session.renderer_name  # pinned for the dataset before the attempt started
    compression = ctx.settings.shard_compression
    key = shard_key(dataset_id, shard.index, compression)

    def cancelled() -> bool:
        if marker.answered:
            raise _MarkerAnswered
        return ctx.records.state(dataset_id) == CANCELLED

    with tempfile.TemporaryDirectory(prefix="seasynth-shard-") as work:
        tar, keep = Path(work) / "shard.tar", (Path(work) / "frames" if spec.outputs.exports else None)
        try:
            with open(tar, "wb") as f:
                sha, size = pack_tar(shard_files(ctx.session, spec, shard, cancelled, keep), f, compression)
            packed = [] if keep is None else pack_parts(spec, shard, keep, Path(work), rec.code_version)
        except _MarkerAnswered:
            pass
        except Exception:  # cancelled, or a frame failed: a marker found meanwhile still counts
            if marker.result() is None:
                raise
        found = marker.result()  # the read's error, if it failed, fails the attempt here
        if found is not None:  # a marker Redis does not know (e.g. Redis lost it): count it now
            _count_marker(ctx, dataset_id, found)
            return Outcome.ALREADY_COMMITTED
        if ctx.records.state(dataset_id) == CANCELLED:
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


# --- reconciling


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
    handed_back = ctx.records.handed_back(dataset_id, pending)
    stall = ctx.settings.stall_s
    return [i for i, t in zip(pending, handed_back) if t is None or now - t >= stall]


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
    spec = ctx.spec(dataset_id, rec.spec)
    files = ctx.session.frame_files(spec, index)
    name = frame_file(part, index, spec.outputs.image_suffix)
    if name not in files:
        raise NotFound(f"frame {index} of dataset {dataset_id} has no {name} (is that output switched on?)")
    return {"ok": True, "name": name, "renderer": ctx.session.renderer_name}, files[name]


def frame_reply(ctx: ShardContext, dataset_id: str, index: int, part: str) -> tuple[dict[str, Any], bytes]:
    """render_frame's answer, or the failure the API maps to a status: 404 (no such frame or file), 422 (the
    dataset's spec or files cannot render it), 503 (another renderer's dataset), 500 (rendering failed).
    WrongVersion is raised: the task sends the request on to that version's queue."""
    try:
        return render_frame(ctx, dataset_id, index, part)
    except WrongVersion:
        raise
    except WrongRenderer as wrong:
        return {"ok": False, "status": 503, "error": str(wrong)}, b""
    except NotFound as err:
        return {"ok": False, "status": 404, "error": str(err)}, b""
    except INPUT_ERRORS as err:
        return {"ok": False, "status": 422, "error": str(err)}, b""
    except Exception as err:
        log.exception("frame %s of dataset %s failed", index, dataset_id)
        return {"ok": False, "status": 500, "error": f"{type(err).__name__}: {err}"}, b""
