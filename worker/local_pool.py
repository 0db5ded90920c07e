"""The local generate's render processes: frames handed out in chunks over a queue, progress, errors and Ctrl-C
reported back to the parent, which alone decides (worker.generate)."""

from __future__ import annotations

import os
import queue
import signal
import tempfile
from pathlib import Path

from service.errors import OutputError, SeasynthError
from service.gpus import GpuChoice
from service.spec import DatasetSpec
from worker.generate import CHUNK, write_frame, wrong_renderer
from worker.pipeline import RenderSession
from worker.pool_start import pool_context, sigint_blocked_for_children


def run_pool(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin) -> str:
    """Render `todo` with `workers` processes sharing terrain variants through a temporary folder (none where no
    temporary folder can be made: each process then keeps its own)."""
    try:
        folder = tempfile.TemporaryDirectory(prefix="seasynth-variants-", ignore_cleanup_errors=True)
    except OSError:
        return _run_pool_in(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, None)
    with folder as variants:
        return _run_pool_in(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, variants)


def _run_pool_in(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, variants: str | None) -> str:
    ctx = pool_context()
    tasks, results = ctx.Queue(), ctx.Queue()
    chunks = [todo[k : k + CHUNK] for k in range(0, len(todo), CHUNK)]
    for c in chunks:
        tasks.put(c)
    workers = min(workers, len(chunks))
    for _ in range(workers):
        tasks.put(None)
    payload = spec.model_dump_json()
    # Daemonic: should this process exit on an unforeseen path, its workers are stopped, not waited for.
    env = dict(os.environ)  # as this process has it now, not as the fork server had it when it started
    procs = [ctx.Process(target=_pool_main, args=(payload, str(out), tasks, results, platform, gpus, k, pinned,
                                                  env, variants), daemon=True) for k in range(workers)]
    renderer, done, finished = "", 0, 0
    try:
        with sigint_blocked_for_children():
            for p in procs:
                p.start()
        while finished < workers:
            try:
                kind, value = results.get(timeout=1.0)
            except queue.Empty:
                # Every worker says "done" before it exits, so any exited process (finished is counted only
                # after the queue drains) whose "done" never came was lost, whatever its exit code.
                exited = sum(p.exitcode is not None for p in procs)
                if exited > finished and results.empty():
                    code = next(p.exitcode for p in procs if p.exitcode is not None)
                    raise SeasynthError(f"a local worker stopped before finishing its frames (exit code {code})")
                continue
            if kind == "frames":
                done += value
                on_frames(value)
            elif kind == "renderer":
                pin(value)
                renderer = value
            elif kind == "done":
                finished += 1
            elif kind == "error":
                raise _rebuild_error(value)
    finally:
        started = [p for p in procs if p.pid is not None]
        if finished < workers:  # stopped early: an error, a lost worker, or Ctrl-C
            tasks.cancel_join_thread()  # chunks nobody will read must not hold up this process's exit
            for p in started:
                if p.is_alive():
                    p.terminate()
        for p in started:
            p.join()
        if finished < workers:
            for p in started:  # a worker stopped mid-write leaves its temporary file
                for tmp in Path(out).glob(f"*/.*.tmp-{p.pid}"):
                    tmp.unlink(missing_ok=True)
    return renderer


def _ignore_sigint() -> None:
    """In a pool worker (started with SIGINT blocked): ignore it from now on; a pending one is dropped."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _pool_main(payload: str, out: str, tasks, results, platform: str, gpus: GpuChoice | None, k: int,
               pinned: str | None, env: dict[str, str], variants: str | None) -> None:
    _ignore_sigint()
    os.environ.clear()
    os.environ.update(env)  # before OpenGL is imported: it reads PYOPENGL_PLATFORM once
    spec = DatasetSpec.model_validate_json(payload)
    try:
        from worker.render.devices import platform_for_worker  # lists EGL devices here, never in the parent

        with RenderSession(platform=platform_for_worker(platform, gpus, k), variant_folder=variants) as session:
            if pinned is not None and session.renderer_name != pinned:  # checked here: workers write frames
                raise OutputError(wrong_renderer(out, pinned, session.renderer_name))
            results.put(("renderer", session.renderer_name))
            while (chunk := tasks.get()) is not None:
                for i in chunk:
                    write_frame(Path(out), session.frame_files(spec, i))
                results.put(("frames", len(chunk)))
    except BaseException as err:  # report every failure to the parent, which decides
        results.put(("error", (type(err).__module__, type(err).__qualname__, str(err))))
        return
    results.put(("done", None))


def _rebuild_error(value: tuple[str, str, str]) -> Exception:
    module, name, message = value
    from service import errors

    cls = getattr(errors, name, None) if module == errors.__name__ else None
    if cls is None:
        from worker.scene import SceneError

        cls = SceneError if name == "SceneError" else SeasynthError
        message = message if cls is SceneError else f"{name}: {message}"
    return cls(message)
