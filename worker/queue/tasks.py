"""Thin Celery tasks over seasynth.worker.queue.shard: plan a dataset, render a shard, render one frame, reconcile."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import tempfile
import threading
import time
from pathlib import Path

from celery import Celery
from celery.exceptions import Reject, Retry
from celery.signals import worker_process_init, worker_process_shutdown

from seasynth.service import __version__
from seasynth.service.errors import NotFound, Unreachable
from seasynth.service.queues import TASK_FRAME, TASK_PLAN, TASK_PREVIEW, TASK_RECONCILE, TASK_SHARD, frame_queue, shard_queue
from seasynth.service.records.types import TERMINAL
from seasynth.service.records.store import Records, push_reply, raw_client
from seasynth.service.settings import Settings
from seasynth.service.shards import shard_at
from seasynth.service.storage import open_store
from seasynth.worker.queue.asset_cache import AssetCache
from seasynth.worker.queue.metrics import TimedFrames, TimedStore, WorkerMetrics
from seasynth.worker.preview.playground import preview_reply
from seasynth.worker.queue.pinning import HEARTBEAT_S, defer_to_renderer
from seasynth.worker.queue.shard import frame_reply, reconcile, run_shard, sweepable
from seasynth.worker.queue.context import Outcome, RetryShard, ShardContext, WrongRenderer, WrongVersion

log = logging.getLogger(__name__)

# A shard pinned to another renderer goes back to the queue after this delay, so that workers of the wrong
# renderer do not pass it around in a tight loop while the right ones are busy.
OTHER_RENDERER_DELAY_S = 5


class Heartbeat:
    """A thread that notes this process's renderer in Redis every HEARTBEAT_S, so that workers of other renderers
    can tell whether a dataset pinned to it still has a live shard worker
    (seasynth.worker.queue.pinning.defer_to_renderer)."""

    def __init__(self, records: Records, version: str, renderer: str):
        self._records = records
        self._args = (version, renderer)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="seasynth-heartbeat", daemon=True)

    def __enter__(self) -> Heartbeat:
        # At once: the first shard may arrive before the first beat.
        self._records.note_renderer(*self._args, time.time())
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                self._records.note_renderer(*self._args, time.time())
            except Exception as err:  # Redis briefly away: the next beat tries again; a long outage shows as gone
                log.warning("renderer heartbeat not noted: %s: %s", type(err).__name__, err)


class RendererUnavailable(Exception):
    """This process's render session could not be opened; it must take no work."""


class ProcessResources:
    """The pool process's ShardContext: opened on worker_process_init (after the fork), closed on shutdown.

    A pool process whose render session fails to open (no GL) takes no work: it stops the whole worker (SIGTERM to
    the main process, which then hands back what it holds and exits with status 1), and any task it still gets is
    rejected back to the queue uncounted. Restart policies (compose, Kubernetes) then show a failing worker instead
    of one that drains the queue.
    """

    def __init__(self, settings: Settings):
        self.settings = settings
        # Whether this worker consumes the shard queue (run_worker sets it before the pool forks): only shard
        # workers count as live workers of their renderer.
        self.takes_shards = True
        self._ctx: ShardContext | None = None
        self.metrics: WorkerMetrics | None = None
        self.frames: TimedFrames | None = None
        self._stack: contextlib.ExitStack | None = None
        self.broken: str | None = None
        # Shared with the pool processes forked later: set when one of them could not open its renderer.
        self.renderer_failed = multiprocessing.RawValue("b", 0)
        self.variant_folder: str | None = None  # set before the pool forks (seasynth.worker.queue.app)

    def open(self) -> None:
        from celery.utils.log import current_process_index

        from seasynth.worker.frame.function import RenderSession  # GL comes up here, in the pool process, never before fork
        from seasynth.worker.render.devices import platform_for_worker

        s = self.settings
        # Pool process k of the prefork pool (a replacement takes the index it frees; a solo pool is 0) renders on
        # the k-th of the settings' GPUs, round robin.
        platform = platform_for_worker(s.gl_platform, s.gpu_choice, current_process_index(base=0) or 0)
        with contextlib.ExitStack() as stack:
            store = open_store(s)
            folder = s.asset_cache_dir or Path(
                stack.enter_context(tempfile.TemporaryDirectory(prefix="seasynth-assets-"))
            )
            session = stack.enter_context(RenderSession(fetch_asset=AssetCache(store, folder), platform=platform,
                                                        variant_folder=self.variant_folder))
            records = Records.from_url(s.redis_url, s.key_prefix)
            raw = raw_client(s.redis_url)
            metrics = WorkerMetrics()  # after the fork: multiprocess mode writes this process's own files
            frames = TimedFrames(session, metrics)
            ctx = ShardContext(settings=s, records=records, raw_redis=raw, store=TimedStore(store, metrics),
                               session=frames)
            if self.takes_shards:
                stack.enter_context(Heartbeat(records, ctx.code_version, session.renderer_name))
            self._ctx, self.metrics, self.frames = ctx, metrics, frames
            self._stack = stack.pop_all()
        log.info("render session ready: %s (%s)", session.renderer_name, platform)

    def open_in_pool_process(self) -> None:
        """worker_process_init: open, or stop the worker that this pool process belongs to."""
        try:
            self.open()
        except Unreachable as err:
            # The bucket is away (an outage), not the renderer: this process opens on its first task instead (the
            # `ctx` property), and until then hands tasks back. Stopping the worker here would take a healthy
            # worker out whenever a pool process is replaced during an outage.
            log.warning("pool process resources not opened, the bucket is unreachable (%s: %s); opening on the "
                        "first task", type(err).__name__, err)
        except Exception as err:
            self.broken = f"{type(err).__name__}: {err}"
            self.renderer_failed.value = 1
            log.critical("render session failed to open (%s): stopping this worker so it takes no shards",
                         self.broken, exc_info=True)
            os.kill(os.getppid(), signal.SIGTERM)  # the prefork pool's parent is the worker's main process

    def close(self) -> None:
        if self._stack is not None:
            self._stack.close()
        self._stack = self._ctx = None

    def count_shard(self, dataset_id: str, shard_index: int, outcome: str, rendered: int) -> None:
        """Count one shard execution that ended with `outcome`; `rendered`: frames it rendered."""
        if self.metrics is None:
            return
        self.metrics.shards.labels(outcome).inc()
        if outcome == Outcome.COMMITTED.value:  # this execution rendered the shard's frames, each once
            self.metrics.frames.labels("committed").inc(rendered)
        elif outcome == Outcome.FAILED.value:
            try:
                rec = self.ctx.records.get(dataset_id)
            except Exception as err:  # the dataset was deleted meanwhile, or Redis is away: the shard count stands
                log.warning("frames of failed shard %s of dataset %s not counted: %s: %s", shard_index, dataset_id,
                            type(err).__name__, err)
                return
            self.metrics.frames.labels("failed").inc(shard_at(rec.frames_total, rec.shard_size, shard_index)
                                                     .frame_count)

    @property
    def ctx(self) -> ShardContext:
        if self._ctx is None:
            if self.broken is not None:
                raise RendererUnavailable(self.broken)
            try:
                self.open()  # a solo/threads pool or a test never fires worker_process_init
            except Unreachable as err:  # an outage: the next task tries again
                raise RendererUnavailable(f"{type(err).__name__}: {err}") from err
            except Exception as err:
                self.broken = f"{type(err).__name__}: {err}"
                raise RendererUnavailable(self.broken) from err
        return self._ctx


def register(app: Celery, settings: Settings) -> ProcessResources:
    """Register the tasks on `app`; they share one ProcessResources per pool process."""
    res = ProcessResources(settings)
    worker_process_init.connect(lambda **_: res.open_in_pool_process(), weak=False)
    worker_process_shutdown.connect(lambda **_: res.close(), weak=False)
    bulk = shard_queue(__version__)

    def ctx_or_reject() -> ShardContext:
        try:
            return res.ctx
        except RendererUnavailable:
            raise Reject("no renderer in this process", requeue=True) from None

    @app.task(name=TASK_SHARD, shared=False, bind=True, acks_late=True, reject_on_worker_lost=True, max_retries=None)
    def render_shard(self, dataset_id: str, shard_index: int, sweep: bool = False) -> str:
        ctx = ctx_or_reject()
        rendered = res.frames.rendered if res.frames is not None else 0
        try:
            ended = run_shard(ctx, dataset_id, shard_index, sweep).value
        except RetryShard as retry:
            res.count_shard(dataset_id, shard_index, "retry", 0)
            # Our attempt counter bounds retries; the delay stays far below the visibility timeout.
            raise self.retry(countdown=retry.countdown, exc=retry) from None
        except WrongVersion as wrong:
            # The flag only when set: workers of older versions take two arguments.
            args = [dataset_id, shard_index] + ([True] if sweep else [])
            app.send_task(TASK_SHARD, args=args, queue=shard_queue(wrong.version))
            return "requeued"
        except WrongRenderer as wrong:
            try:
                outcome = defer_to_renderer(ctx, dataset_id, shard_index, wrong)
            except Exception:  # the bookkeeping failed (Redis away): hand the shard back all the same
                log.exception("shard %s of dataset %s: hand-back not recorded", shard_index, dataset_id)
                outcome = Outcome.DEFERRED
            if outcome is not Outcome.DEFERRED:
                log.warning("shard %s of dataset %s: %s; %s", shard_index, dataset_id, wrong, outcome.value)
                return outcome.value
            log.info("shard %s: %s; handed back", shard_index, wrong)
            render_shard.apply_async((dataset_id, shard_index, sweep), queue=bulk, countdown=OTHER_RENDERER_DELAY_S)
            return "requeued"
        except Exception as err:
            # run_shard counts every failure it can; this one escaped it (e.g. Redis was unreachable while counting).
            # Never let Celery drop the message: publish it again, or hand it back if even that fails.
            log.exception("shard %s of dataset %s: failure not counted; running it again", shard_index, dataset_id)
            try:
                raise self.retry(countdown=settings.retry_backoff_max_s, exc=err)
            except Retry:
                raise
            except Exception:
                time.sleep(1)  # the broker is probably down too: do not spin
                raise Reject(f"{type(err).__name__}: {err}", requeue=True) from err
        # Outside the try: counting never sends an ended shard round again.
        res.count_shard(dataset_id, shard_index, ended, res.frames.rendered - rendered if res.frames else 0)
        return ended

    @app.task(name=TASK_PLAN, shared=False, acks_late=True, reject_on_worker_lost=True)
    def plan_dataset(dataset_id: str, first_shard: int = 0, sweep: bool = False) -> int:
        """Publish one batch of shard tasks, then a planner for the next batch; returns messages published (none
        for a dataset that is gone or final: cancelled, succeeded or failed).

        `sweep` (the reconciler): only the shards still pending and not going round between workers of another
        renderer (seasynth.worker.queue.shard.sweepable), marked so that they defer to a running execution.
        """
        ctx = ctx_or_reject()
        try:
            rec = ctx.records.get(dataset_id)
        except NotFound:
            return 0
        if rec.state in TERMINAL:  # cancelled, or every shard already committed or failed
            return 0
        end = min(first_shard + settings.plan_batch, rec.shards_total)
        batch = list(range(first_shard, end))
        if sweep:
            batch = sweepable(ctx, dataset_id, batch, time.time())
        ctx.records.touch(dataset_id, time.time())
        with app.producer_or_acquire() as producer:
            for i in batch:
                render_shard.apply_async((dataset_id, i, sweep), queue=bulk, producer=producer)
            if end < rec.shards_total:
                plan_dataset.apply_async((dataset_id, end, sweep), queue=bulk, producer=producer)
        return len(batch)

    def frame_ctx(task: str, args: list) -> ShardContext | None:
        """This process's resources; None when it has no renderer, after publishing the task again for another
        frame worker (frames-queue tasks are acknowledged early)."""
        try:
            return res.ctx
        except RendererUnavailable:
            app.send_task(task, args=args, queue=frame_queue(__version__))
            return None

    reply_ttl_s = int(settings.frame_timeout_s) + 60

    @app.task(name=TASK_FRAME, shared=False, acks_late=False)
    def render_frame_task(dataset_id: str, frame_index: int, part: str, reply_key: str) -> None:
        if (ctx := frame_ctx(TASK_FRAME, [dataset_id, frame_index, part, reply_key])) is None:
            return
        try:
            header, body = frame_reply(ctx, dataset_id, frame_index, part)
        except WrongVersion as wrong:
            app.send_task(TASK_FRAME, args=[dataset_id, frame_index, part, reply_key], queue=frame_queue(wrong.version))
            return
        push_reply(ctx.raw_redis, reply_key, header, body, ttl_s=reply_ttl_s)

    @app.task(name=TASK_PREVIEW, shared=False, acks_late=False)
    def render_preview_task(kind: str, spec_json: dict, args: list, reply_key: str) -> None:
        """A playground render (seasynth.worker.preview.playground), answered on `reply_key` as JSON."""
        if (ctx := frame_ctx(TASK_PREVIEW, [kind, spec_json, args, reply_key])) is None:
            return
        header, body = preview_reply(ctx.session, kind, spec_json, args)
        push_reply(ctx.raw_redis, reply_key, header, body, ttl_s=reply_ttl_s)

    @app.task(name=TASK_RECONCILE, shared=False, acks_late=True)
    def reconcile_dataset(dataset_id: str, requeue: bool = False) -> int:
        """Adopt missed commits, finalise if complete; with requeue, publish the pending shards again (through
        the planner, batch by batch). Returns how many shards were pending."""
        pending = reconcile(ctx_or_reject(), dataset_id)
        if requeue and pending:
            plan_dataset.apply_async((dataset_id, 0, True), queue=bulk)
        return len(pending)

    return res
