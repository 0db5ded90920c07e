"""A worker process's resources: the ShardContext its tasks share (records, storage, render session, asset cache,
metrics), opened once per pool process after the fork and closed at its shutdown, and the renderer heartbeat."""

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

from seasynth.service.errors import Unreachable
from seasynth.service.records.store import Records, raw_client
from seasynth.service.settings import Settings
from seasynth.service.shards import shard_at
from seasynth.service.storage import open_store
from seasynth.worker.queue.asset_cache import AssetCache
from seasynth.worker.queue.context import Outcome, ShardContext
from seasynth.worker.queue.metrics import TimedFrames, TimedStore, WorkerMetrics
from seasynth.worker.queue.pinning import HEARTBEAT_S

log = logging.getLogger(__name__)


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

        from seasynth.worker.frame.function import (
            RenderSession,  # GL comes up here, in the pool process, never before fork
        )
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
