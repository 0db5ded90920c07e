"""The workers' Celery app: its configuration guards against lost and duplicated work, its tasks are defined at
module level on one base that holds the process's resources, and the settings it reads (SEASYNTH_*) parse as the
worker always parsed them."""

from __future__ import annotations

import pytest

from seasynth.service.queues import TASK_FRAME, TASK_PLAN, TASK_PREVIEW, TASK_RECONCILE, TASK_SHARD
from seasynth.service.settings import WORKER_MAX_MEMORY_PER_CHILD_MB, Settings


def test_celery_configuration_guards_against_lost_and_duplicated_work(infra):
    from seasynth.service.queues import frame_queue, shard_queue
    from seasynth.worker.queue.app import create_app, worker_argv

    s = infra.settings(task_time_limit_s=600)
    conf = create_app(s).conf
    assert conf.task_acks_late and conf.task_reject_on_worker_lost and conf.worker_prefetch_multiplier == 1
    assert conf.worker_cancel_long_running_tasks_on_connection_loss
    assert conf.task_time_limit == 600 and conf.task_soft_time_limit == 540
    assert conf.broker_transport_options["visibility_timeout"] >= 3 * conf.task_time_limit
    assert conf.task_ignore_result and not conf.result_backend
    a, b = worker_argv(2, ["shards", "frames"]), worker_argv(2, ["shards", "frames"])
    name = next(x for x in a if x.startswith("--hostname="))
    assert name != next(x for x in b if x.startswith("--hostname=")) and "--pool=prefork" in a
    from seasynth.service import __version__

    assert f"--queues={shard_queue(__version__)},{frame_queue(__version__)}" in a
    assert __version__ in shard_queue(__version__)


def test_hard_time_limit_requeues_the_message(infra):
    """Celery acks a late-acked message at the hard time limit by default: the shard would be lost."""
    from celery.contrib.testing.mocks import TaskMessage
    from celery.worker.request import Request

    from seasynth.worker.queue.app import create_app

    app = create_app(infra.settings())
    task = app.tasks[TASK_SHARD]
    assert task.acks_late and task.acks_on_timeout is False and task.acks_on_failure is False
    message = TaskMessage(TASK_SHARD, args=["a" * 32, 0])
    request = Request(message, app=app, task=task, on_ack=message.ack_log_error, on_reject=message.reject_log_error)
    request.on_timeout(soft=False, timeout=300)
    assert not message.ack_log_error.called
    (_, _, requeue), _ = message.reject_log_error.call_args  # (logger, connection errors, requeue)
    assert requeue is True


def test_pool_processes_are_recycled_by_memory(infra, monkeypatch):
    from seasynth.worker.queue.app import create_app

    assert create_app(infra.settings()).conf.worker_max_memory_per_child == WORKER_MAX_MEMORY_PER_CHILD_MB * 1024
    monkeypatch.setenv("SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB", "3000")
    assert create_app(infra.settings()).conf.worker_max_memory_per_child == 3000 * 1024
    monkeypatch.setenv("SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB", "lots")
    with pytest.raises(ValueError, match="SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB"):
        create_app(infra.settings())


def test_the_tasks_live_at_module_level_on_one_base_with_their_options(infra):
    from seasynth.worker.queue import tasks
    from seasynth.worker.queue.app import create_app

    app = create_app(infra.settings())
    options = {name: (type(t).__mro__[1], t.run.__module__, t.acks_late, t.reject_on_worker_lost, t.max_retries)
               for name, t in app.tasks.items() if name.startswith("seasynth.")}
    base, module = tasks.SeasynthTask, tasks.__name__
    assert options == {TASK_SHARD: (base, module, True, True, None), TASK_PLAN: (base, module, True, True, 3),
                       TASK_FRAME: (base, module, False, True, 3), TASK_PREVIEW: (base, module, False, True, 3),
                       TASK_RECONCILE: (base, module, True, True, 3)}
    assert {name: getattr(tasks, t.run.__name__) for name, t in app.tasks.items() if name.startswith("seasynth.")} \
        == {name: t for name, t in app.tasks.items() if name.startswith("seasynth.")}
    # One ProcessResources per process, for the settings the app was configured with, shared by every task.
    shared = {id(t.resources) for name, t in app.tasks.items() if name.startswith("seasynth.")}
    assert shared == {id(tasks.SeasynthTask._process)} and tasks.SeasynthTask._process.settings == infra.settings()


def test_configuring_again_publishes_to_the_new_broker(infra):
    from seasynth.worker.queue.app import create_app

    first, second = (infra.settings().redis_url.rsplit("/", 1)[0] + f"/{db}" for db in (7, 8))
    app = create_app(infra.settings(redis_url=first))
    with app.producer_or_acquire() as producer:
        assert producer.connection.as_uri().endswith("/7")
    assert create_app(infra.settings(redis_url=second)) is app
    with app.producer_or_acquire() as producer:
        assert producer.connection.as_uri().endswith("/8")
    assert app.pool.connection.as_uri().endswith("/8")


def test_settings_read_the_worker_variables_as_the_worker_did(monkeypatch):
    """SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB and SEASYNTH_RENDERER_WAIT_S: blank is unset, surrounding spaces
    are ignored, and a bad value fails at the entry point naming the variable."""
    for name in ("SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB", "SEASYNTH_RENDERER_WAIT_S"):
        monkeypatch.delenv(name, raising=False)
    s = Settings()
    assert (s.worker_max_memory_per_child_mb, s.renderer_wait_s) == (WORKER_MAX_MEMORY_PER_CHILD_MB, None)
    cases = {("  ", " "): (WORKER_MAX_MEMORY_PER_CHILD_MB, None), (" 3000 ", " 12.5 "): (3000, 12.5),
             ("256", "inf"): (256, float("inf"))}
    for (mb, wait), want in cases.items():
        monkeypatch.setenv("SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB", mb)
        monkeypatch.setenv("SEASYNTH_RENDERER_WAIT_S", wait)
        s = Settings()
        assert (s.worker_max_memory_per_child_mb, s.renderer_wait_s) == want
    monkeypatch.setenv("SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB", "255")
    with pytest.raises(ValueError, match=r"worker_max_memory_per_child_mb: 255 MiB is below a fresh render process"):
        Settings()
    monkeypatch.delenv("SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB")
    for bad, why in {"soon": "not a number of seconds: 'soon'", "0": "must be > 0, got '0'",
                     "-3": "must be > 0, got '-3'", "nan": "must be > 0, got 'nan'"}.items():
        monkeypatch.setenv("SEASYNTH_RENDERER_WAIT_S", bad)
        with pytest.raises(ValueError, match=f"SEASYNTH_RENDERER_WAIT_S: {why}"):
            Settings()
