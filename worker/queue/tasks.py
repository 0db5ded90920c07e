"""Thin Celery tasks over seasynth.worker.queue.shard: plan a dataset, render a shard, render one frame, reconcile.

They are defined at module level on the workers' app (seasynth.worker.queue.celery_app), on the SeasynthTask base,
which holds the worker process's resources (ProcessResources: records, storage, render session, asset cache).
"""

from __future__ import annotations

import logging
import time
from typing import ClassVar

from celery import Task
from celery.exceptions import Reject, Retry
from celery.signals import worker_process_init, worker_process_shutdown

from seasynth.service import __version__
from seasynth.service.errors import NotFound
from seasynth.service.queues import (
    TASK_FRAME,
    TASK_PLAN,
    TASK_PREVIEW,
    TASK_RECONCILE,
    TASK_SHARD,
    frame_queue,
    shard_queue,
)
from seasynth.service.records.store import push_reply
from seasynth.service.records.types import TERMINAL
from seasynth.service.settings import Settings
from seasynth.worker.preview.playground import preview_reply
from seasynth.worker.queue.celery_app import app
from seasynth.worker.queue.context import Outcome, RetryShard, ShardContext, WrongRenderer, WrongVersion
from seasynth.worker.queue.pinning import defer_to_renderer
from seasynth.worker.queue.process import ProcessResources, RendererUnavailable
from seasynth.worker.queue.shard import frame_reply, reconcile, run_shard, sweepable

log = logging.getLogger(__name__)

# A shard pinned to another renderer goes back to the queue after this delay, so that workers of the wrong
# renderer do not pass it around in a tight loop while the right ones are busy.
OTHER_RENDERER_DELAY_S = 5


class SeasynthTask(Task):
    """Base of the workers' tasks: they share this process's ProcessResources, made for the worker's settings before
    the pool forks (use), opened in each pool process after the fork (or by the first task, in a solo pool) and
    closed at its shutdown."""

    _process: ClassVar[ProcessResources | None] = None

    @staticmethod
    def use(settings: Settings) -> ProcessResources:
        """Make this process's resources for `settings`, opened and closed with each pool process."""
        SeasynthTask._process = ProcessResources(settings)
        worker_process_init.connect(_open_in_pool_process, weak=False, dispatch_uid="seasynth-process-open")
        worker_process_shutdown.connect(_close_process, weak=False, dispatch_uid="seasynth-process-close")
        return SeasynthTask._process

    @property
    def resources(self) -> ProcessResources:
        if SeasynthTask._process is None:
            raise RuntimeError("the worker app is not configured: seasynth.worker.queue.app.create_app(settings)")
        return SeasynthTask._process

    def ctx_or_reject(self) -> ShardContext:
        """This process's resources; a process without a renderer rejects the task back to the queue."""
        try:
            return self.resources.ctx
        except RendererUnavailable:
            raise Reject("no renderer in this process", requeue=True) from None

    def frame_ctx(self, args: list) -> ShardContext | None:
        """This process's resources; None when it has no renderer, after publishing the task again for another
        frame worker (frames-queue tasks are acknowledged early)."""
        try:
            return self.resources.ctx
        except RendererUnavailable:
            self.app.send_task(self.name, args=args, queue=frame_queue(__version__))
            return None

    def reply_ttl_s(self) -> int:
        """How long a single-frame answer waits in Redis: the API's wait and a minute."""
        return int(self.resources.settings.frame_timeout_s) + 60


def _open_in_pool_process(**_: object) -> None:
    if SeasynthTask._process is not None:
        SeasynthTask._process.open_in_pool_process()


def _close_process(**_: object) -> None:
    if SeasynthTask._process is not None:
        SeasynthTask._process.close()


@app.task(base=SeasynthTask, name=TASK_SHARD, shared=False, bind=True, acks_late=True, reject_on_worker_lost=True,
          max_retries=None)
def render_shard(self: SeasynthTask, dataset_id: str, shard_index: int, sweep: bool = False) -> str:
    ctx = self.ctx_or_reject()
    res = self.resources
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
        self.app.send_task(TASK_SHARD, args=args, queue=shard_queue(wrong.version))
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
        render_shard.apply_async((dataset_id, shard_index, sweep), queue=shard_queue(__version__),
                                 countdown=OTHER_RENDERER_DELAY_S)
        return "requeued"
    except Exception as err:
        # run_shard counts every failure it can; this one escaped it (e.g. Redis was unreachable while counting).
        # Never let Celery drop the message: publish it again, or hand it back if even that fails.
        log.exception("shard %s of dataset %s: failure not counted; running it again", shard_index, dataset_id)
        try:
            raise self.retry(countdown=res.settings.retry_backoff_max_s, exc=err)
        except Retry:
            raise
        except Exception:
            time.sleep(1)  # the broker is probably down too: do not spin
            raise Reject(f"{type(err).__name__}: {err}", requeue=True) from err
    # Outside the try: counting never sends an ended shard round again.
    res.count_shard(dataset_id, shard_index, ended, res.frames.rendered - rendered if res.frames else 0)
    return ended


@app.task(base=SeasynthTask, name=TASK_PLAN, shared=False, bind=True, acks_late=True, reject_on_worker_lost=True)
def plan_dataset(self: SeasynthTask, dataset_id: str, first_shard: int = 0, sweep: bool = False) -> int:
    """Publish one batch of shard tasks, then a planner for the next batch; returns messages published (none
    for a dataset that is gone or final: cancelled, succeeded or failed).

    `sweep` (the reconciler): only the shards still pending and not going round between workers of another
    renderer (seasynth.worker.queue.shard.sweepable), marked so that they defer to a running execution.
    """
    ctx = self.ctx_or_reject()
    try:
        rec = ctx.records.get(dataset_id)
    except NotFound:
        return 0
    if rec.state in TERMINAL:  # cancelled, or every shard already committed or failed
        return 0
    end = min(first_shard + self.resources.settings.plan_batch, rec.shards_total)
    batch = list(range(first_shard, end))
    if sweep:
        batch = sweepable(ctx, dataset_id, batch, time.time())
    ctx.records.touch(dataset_id, time.time())
    bulk = shard_queue(__version__)
    with self.app.producer_or_acquire() as producer:
        for i in batch:
            render_shard.apply_async((dataset_id, i, sweep), queue=bulk, producer=producer)
        if end < rec.shards_total:
            plan_dataset.apply_async((dataset_id, end, sweep), queue=bulk, producer=producer)
    return len(batch)


@app.task(base=SeasynthTask, name=TASK_FRAME, shared=False, bind=True, acks_late=False)
def render_frame_task(self: SeasynthTask, dataset_id: str, frame_index: int, part: str, reply_key: str) -> None:
    if (ctx := self.frame_ctx([dataset_id, frame_index, part, reply_key])) is None:
        return
    try:
        header, body = frame_reply(ctx, dataset_id, frame_index, part)
    except WrongVersion as wrong:
        self.app.send_task(TASK_FRAME, args=[dataset_id, frame_index, part, reply_key],
                           queue=frame_queue(wrong.version))
        return
    push_reply(ctx.raw_redis, reply_key, header, body, ttl_s=self.reply_ttl_s())


@app.task(base=SeasynthTask, name=TASK_PREVIEW, shared=False, bind=True, acks_late=False)
def render_preview_task(self: SeasynthTask, kind: str, spec_json: dict, args: list, reply_key: str) -> None:
    """A playground render (seasynth.worker.preview.playground), answered on `reply_key` as JSON."""
    if (ctx := self.frame_ctx([kind, spec_json, args, reply_key])) is None:
        return
    header, body = preview_reply(ctx.session, kind, spec_json, args)
    push_reply(ctx.raw_redis, reply_key, header, body, ttl_s=self.reply_ttl_s())


@app.task(base=SeasynthTask, name=TASK_RECONCILE, shared=False, bind=True, acks_late=True)
def reconcile_dataset(self: SeasynthTask, dataset_id: str, requeue: bool = False) -> int:
    """Adopt missed commits, finalise if complete; with requeue, publish the pending shards again (through
    the planner, batch by batch). Returns how many shards were pending."""
    pending = reconcile(self.ctx_or_reject(), dataset_id)
    if requeue and pending:
        plan_dataset.apply_async((dataset_id, 0, True), queue=shard_queue(__version__))
    return len(pending)
