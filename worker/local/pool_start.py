"""How the local generate's render processes start (seasynth.worker.local.pool), in a module light enough for the command
line to start the fork server before it imports the pipeline itself: the two imports then overlap.

Render processes are forked from a server that has imported seasynth.worker.local.pool (and with it numpy, trimesh, scipy
and the pipeline; never OpenGL). A process that imports them itself took 2 s on a 16-core H100 host and 3.5-4.6 s
with 24 doing it at once (bench/results/gpu/startup.md). The server never opens a GL context, so none crosses a
fork. Where there is no fork server, each process starts fresh (spawn).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import signal
import sys
import threading
from collections.abc import Iterator

PRELOAD = "seasynth.worker.local.pool"


# multiprocessing's resource tracker (a process of its own, started with this interpreter's -W options) warns at exit
# of a named semaphore it still tracks but finds already unlinked: with the fork server this happened now and then
# after a Ctrl-C (python/cpython#98268) while the pool's IPC was multiprocessing queues, although nothing was left
# behind. The pool now talks over pipes, which hold no named semaphore; the filter stays for any other
# multiprocessing object a caller makes. The tracker's cleanup stays; only that warning goes.
QUIET_TRACKER = "ignore::UserWarning:multiprocessing.resource_tracker"


def pool_context():
    """The multiprocessing context of the render processes."""
    if QUIET_TRACKER not in sys.warnoptions:
        sys.warnoptions.append(QUIET_TRACKER)  # read when the tracker starts, which is after this
    if "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload([PRELOAD])
        return ctx
    return mp.get_context("spawn")


def start_early() -> None:
    """Start the fork server now (it imports the pipeline meanwhile), with SIGINT blocked as the render processes
    must begin: they inherit the server's mask."""
    ctx = pool_context()
    if ctx.get_start_method() == "forkserver":
        from multiprocessing import forkserver

        with sigint_blocked_for_children():
            forkserver.ensure_running()


@contextlib.contextmanager
def sigint_blocked_for_children() -> Iterator[None]:
    """Processes started inside begin with SIGINT blocked, imports included (a signal mask survives fork and exec),
    and seasynth.worker.local.pool's `_pool_main` ignores it before unblocking: Ctrl-C reaches the whole process group, but
    only this process acts on it, and it stops the workers. The fork server is started inside too (its children
    inherit its mask), and ignores SIGINT itself.

    Only this thread's mask changes. Setting SIGINT's disposition to SIG_IGN here instead would lose a Ctrl-C that
    came meanwhile: another thread of this process (the progress bar's) would take it and discard
    it. Blocked, it waits for this thread or is handled by another, and Python raises it in the main thread.
    """
    if threading.current_thread() is not threading.main_thread():  # signals are the main thread's business
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
