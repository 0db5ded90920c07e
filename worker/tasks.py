"""Thin Celery tasks over worker.shard: plan a dataset, render a shard, render one frame, reconcile."""

from __future__ import annotations

import contextlib
import logging
import tempfile
from pathlib import Path

from celery import Celery
from celery.signals import worker_process_init, worker_process_shutdown

from service import __version__
from service.errors import NotFound
from service.queues import TASK_FRAME, TASK_PLAN, TASK_RECONCILE, TASK_SHARD, frame_queue, shard_queue
from service.records import CANCELLED, Records, push_reply
from service.settings import Settings
from service.storage import open_store
from worker.shard import AssetCache, RetryShard, ShardContext, WrongVersion, reconcile, render_frame, run_shard

log = logging.getLogger(__name__)


class ProcessResources:
    """The pool process's ShardContext: opened on worker_process_init (after the fork), closed on shutdown."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self._ctx: ShardContext | None = None
        self._stack: contextlib.ExitStack | None = None

    def open(self) -> None:
        import redis

        from worker.pipeline import RenderSession  # GL comes up here, in the pool process, never before fork

        s = self.settings
        stack = contextlib.ExitStack()
        store = open_store(s)
        folder = s.asset_cache_dir or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="seasynth-assets-")))
        session = stack.enter_context(RenderSession(fetch_asset=AssetCache(store, folder), platform=s.gl_platform))
        records = Records(redis.Redis.from_url(s.redis_url, decode_responses=True), s.key_prefix)
        raw = redis.Redis.from_url(s.redis_url)
        self._ctx = ShardContext(settings=s, records=records, raw_redis=raw, store=store, session=session)
        self._stack = stack
        log.info("render session ready: %s", session.renderer_name)

    def close(self) -> None:
        if self._stack is not None:
            self._stack.close()
        self._stack = self._ctx = None

    @property
    def ctx(self) -> ShardContext:
        if self._ctx is None:
            self.open()  # a solo/threads pool or a test never fires worker_process_init
        return self._ctx


def register(app: Celery, settings: Settings) -> ProcessResources:
    """Register the tasks on `app`; they share one ProcessResources per pool process."""
    res = ProcessResources(settings)
    worker_process_init.connect(lambda **_: res.open(), weak=False)
    worker_process_shutdown.connect(lambda **_: res.close(), weak=False)
    bulk = shard_queue(__version__)

    @app.task(name=TASK_SHARD, bind=True, acks_late=True, reject_on_worker_lost=True, max_retries=None)
    def render_shard(self, dataset_id: str, shard_index: int) -> str:
        try:
            return run_shard(res.ctx, dataset_id, shard_index).value
        except RetryShard as retry:
            # Our attempt counter bounds retries; the delay stays far below the visibility timeout.
            raise self.retry(countdown=retry.countdown, exc=retry) from None
        except WrongVersion as wrong:
            app.send_task(TASK_SHARD, args=[dataset_id, shard_index], queue=shard_queue(wrong.version))
            return "requeued"

    @app.task(name=TASK_PLAN, acks_late=True, reject_on_worker_lost=True)
    def plan_dataset(dataset_id: str, first_shard: int = 0) -> int:
        """Publish one batch of shard tasks, then a planner for the next batch; returns messages published."""
        ctx = res.ctx
        try:
            rec = ctx.records.get(dataset_id)
        except NotFound:
            return 0
        if rec.state == CANCELLED:
            return 0
        end = min(first_shard + settings.plan_batch, rec.shards_total)
        with app.producer_or_acquire() as producer:
            for i in range(first_shard, end):
                render_shard.apply_async((dataset_id, i), queue=bulk, producer=producer)
            if end < rec.shards_total:
                plan_dataset.apply_async((dataset_id, end), queue=bulk, producer=producer)
        return end - first_shard

    @app.task(name=TASK_FRAME, acks_late=False)
    def render_frame_task(dataset_id: str, frame_index: int, part: str, reply_key: str) -> None:
        ctx = res.ctx
        try:
            header, body = render_frame(ctx, dataset_id, frame_index, part)
        except WrongVersion as wrong:
            app.send_task(TASK_FRAME, args=[dataset_id, frame_index, part, reply_key], queue=frame_queue(wrong.version))
            return
        except NotFound as err:
            header, body = {"ok": False, "status": 404, "error": str(err)}, b""
        except Exception as err:
            log.exception("frame %s of dataset %s failed", frame_index, dataset_id)
            header, body = {"ok": False, "status": 500, "error": f"{type(err).__name__}: {err}"}, b""
        push_reply(ctx.raw_redis, reply_key, header, body, ttl_s=int(settings.frame_timeout_s) + 60)

    @app.task(name=TASK_RECONCILE, acks_late=True)
    def reconcile_dataset(dataset_id: str, requeue: bool = False) -> int:
        """Adopt missed commits, finalise if complete; with requeue, publish the pending shards again."""
        pending = reconcile(res.ctx, dataset_id)
        if requeue:
            with app.producer_or_acquire() as producer:
                for i in pending:
                    render_shard.apply_async((dataset_id, i), queue=bulk, producer=producer)
        return len(pending)

    return res
