"""The Celery app of the render workers: Redis broker, prefork pool, late acks, version-pinned queues.

Configuration follows the broker's known traps (see the project's distributed notes): late acks with rejection on
worker loss plus our own attempt counter, prefetch 1, a visibility timeout of 3x the hard time limit, cancelling
long-running tasks on connection loss, a soft shutdown for scale-down, pool processes recycled after a number of
tasks or once they have grown past a memory size, and no result backend.

Celery acknowledges a late-acked message on failure and on the hard time limit by default; here a task hitting
the hard limit goes back to the queue (its attempt was counted when it started) and the shard task lets no
failure escape uncounted (seasynth.worker.queue.shard.run_shard), so no message is dropped on the way.
"""

from __future__ import annotations

import sys
import uuid

from celery import Celery

from seasynth.service import __version__
from seasynth.service.queues import broker_options, frame_queue, shard_queue
from seasynth.service.settings import Settings
from seasynth.worker.scene.disk_cache import run_folder

QUEUE_KINDS = ("shards", "frames")


def create_app(settings: Settings) -> Celery:
    """The workers' app configured for `settings`, its tasks registered; per-process resources open in each pool
    process after fork."""
    return _build(settings)[0]


def _build(settings: Settings):
    """Configure the module-level app (seasynth.worker.queue.celery_app) and make this process's resources.

    A worker configures it once, before its first task binds its options. Tests configure it again for other
    settings: the broker connections Celery keeps for an earlier broker URL are dropped then."""
    from seasynth.worker.queue import tasks

    app = tasks.app
    if app.conf.broker_url not in (None, settings.redis_url):
        # Celery keeps its broker connection and producer pools per app: drop those of the earlier URL, as Celery
        # itself does after a fork (Celery._after_fork).
        app._pool = None
        app.amqp._producer_pool = None
    app.conf.update(
        broker_url=settings.redis_url,
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,  # status lives in our Redis records
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_timeout=False,  # the hard time limit requeues the message (its attempt is already counted)
        # A failure that escapes a task is rejected unrequeued (on Redis that drops it like an ack would): the shard
        # task lets none escape, it counts and retries, marks the shard failed, or rejects with requeue.
        task_acks_on_failure=False,
        worker_prefetch_multiplier=1,
        worker_max_tasks_per_child=settings.worker_max_tasks_per_child,
        # Celery counts KiB (service/settings.py WORKER_MAX_MEMORY_PER_CHILD_MB says why this size)
        worker_max_memory_per_child=settings.worker_max_memory_per_child_mb * 1024,
        worker_cancel_long_running_tasks_on_connection_loss=True,
        task_soft_time_limit=settings.task_soft_time_limit_s,
        task_time_limit=settings.task_time_limit_s,
        broker_transport_options=broker_options(settings.visibility_timeout_s),
        broker_connection_retry_on_startup=True,
        worker_soft_shutdown_timeout=settings.worker_soft_shutdown_s,
        task_default_queue=shard_queue(__version__),
        worker_hijack_root_logger=True,
        worker_redirect_stdouts=False,
    )
    return app, tasks.SeasynthTask.use(settings)


def worker_argv(concurrency: int, queues: list[str], loglevel: str = "INFO") -> list[str]:
    """Arguments of `celery worker`: a unique node name so any number of workers can share a host."""
    unknown = set(queues) - set(QUEUE_KINDS)
    if unknown:
        raise ValueError(f"unknown queue kind(s) {sorted(unknown)}; choose from {', '.join(QUEUE_KINDS)}")
    names = [shard_queue(__version__) if q == "shards" else frame_queue(__version__) for q in queues]
    return [
        "worker",
        "--pool=prefork",
        f"--concurrency={concurrency}",
        f"--hostname=seasynth-{uuid.uuid4().hex[:12]}@%h",
        f"--queues={','.join(names)}",
        "--without-gossip",
        "--without-mingle",
        f"--loglevel={loglevel}",
    ]


def run_worker(settings: Settings, concurrency: int, queues: list[str] | None = None, loglevel: str = "INFO") -> None:
    """Run a worker in the foreground until it is stopped (SIGTERM: soft shutdown, then warm shutdown).

    Exits with status 1 when a pool process could not open its renderer (it stopped the worker at once).
    With settings.worker_metrics_port, serves the pool processes' Prometheus metrics on it meanwhile.
    """
    from seasynth.worker.queue.metrics import exporter

    with exporter(settings):  # before anything imports prometheus_client, and before the pool forks
        _run(settings, concurrency, list(queues or QUEUE_KINDS), loglevel)


def _run(settings: Settings, concurrency: int, queues: list[str], loglevel: str) -> None:
    app, resources = _build(settings)
    resources.takes_shards = "shards" in queues  # before the pool forks: its processes inherit it
    try:
        # The pool processes share terrain variants and texture sets through the cache folder that outlives runs
        # (seasynth.worker.scene.disk_cache), else through a temporary one that only this process removes (they
        # leave through os._exit).
        with run_folder() as variants:
            resources.variant_folder = variants
            app.worker_main(worker_argv(concurrency, queues, loglevel))
    finally:
        if resources.renderer_failed.value:  # replaces Celery's exit status 0 after the warm shutdown
            sys.exit("seasynth worker: stopped because a render process could not open its renderer (see the log)")


if __name__ == "__main__":  # python -m seasynth.worker.queue.app [concurrency]
    run_worker(Settings(), int(sys.argv[1]) if len(sys.argv) > 1 else 1)
