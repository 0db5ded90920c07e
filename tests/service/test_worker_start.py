"""`seasynth worker --concurrency auto` starts as many render processes as seasynth.worker.local.capacity says fill this machine
(one a core on a CPU-only machine, 1.5 a core on GPUs), listing EGL's devices in a child, never in the worker."""

from __future__ import annotations

import re

from service_stack import wait_worker_ready


def test_concurrency_auto_starts_what_fills_the_machine(infra):
    from seasynth.worker.local.capacity import gpus_found, render_processes

    expected = render_processes(gpus_found("egl", None))
    worker = infra.seasynth("worker", "worker", "--concurrency", "auto", "--queues", "frames", "--loglevel", "INFO")
    try:
        wait_worker_ready(worker, expected, timeout=120)
        log = worker.log.read_text(errors="replace")
        assert re.findall(r"--concurrency auto: (\d+) render processes", log) == [str(expected)]
        assert f"concurrency: {expected} (prefork)" in log and log.count("render session ready") == expected
    finally:
        worker.stop()
