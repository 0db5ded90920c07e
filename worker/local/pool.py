"""The local generate's render processes: frames handed out in chunks over a pipe to each, progress, errors and
Ctrl-C reported back to the parent, which alone decides (seasynth.worker.local.generate)."""

from __future__ import annotations

import contextlib
import os
import signal
from multiprocessing import connection
from pathlib import Path

from seasynth.service import errors
from seasynth.service.errors import OutputError, SeasynthError
from seasynth.service.gpus import GpuChoice
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.local.folder import write_frame, wrong_renderer
from seasynth.worker.local.pool_start import pool_context, sigint_blocked_for_children
from seasynth.worker.render.devices import platform_for_worker
from seasynth.worker.scene.disk_cache import run_folder
from seasynth.worker.scene.sample import SceneError

CHUNK = 4  # frames a local worker takes at a time: small enough to balance, large enough to amortise IPC


def run_pool(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, timeline: str | None = None) -> str:
    """Render `todo` with `workers` processes sharing terrain variants and texture sets through the cache folder
    across runs (disk_cache), else through a temporary folder (none where no temporary folder can be made: each
    process then keeps its own). timeline: a file each process notes its events to (Timeline), or None."""
    try:
        folder = run_folder()
    except OSError:
        return _run_pool_in(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, None, timeline)
    with folder as variants:
        return _run_pool_in(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, variants, timeline)


def _run_pool_in(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, variants: str | None,
                 timeline: str | None) -> str:
    """Each render process has a pipe of its own: the parent hands it a chunk once it has named its renderer (and the
    dataset's pin accepted it: no frame of another renderer is written), and the next when it reports the chunk's
    frames. Pipes hold no named semaphore (a multiprocessing queue does, and with the fork server the
    resource tracker could find one already unlinked after a Ctrl-C), and no feeder thread; and a process that
    ends is seen at once, by the end of its pipe."""
    ctx = pool_context()
    chunks = [todo[k : k + CHUNK] for k in range(0, len(todo), CHUNK)]
    workers = min(workers, len(chunks))
    payload = spec.model_dump_json()
    env = dict(os.environ)  # as this process has it now, not as the fork server had it when it started
    pipes = [ctx.Pipe() for _ in range(workers)]
    # Daemonic: should this process exit on an unforeseen path, its workers are stopped, not waited for.
    procs = [ctx.Process(target=_pool_main, args=(payload, str(out), child, platform, gpus, k, pinned, env,
                                                  variants, timeline), daemon=True)
             for k, (_, child) in enumerate(pipes)]
    conns = [parent for parent, _ in pipes]
    renderer, finished, given = "", 0, 0

    def give(k: int) -> None:  # the next chunk to process k, or None: no more
        nonlocal given
        try:
            conns[k].send(chunks[given] if given < len(chunks) else None)
        except OSError:  # its end is closed: the process has gone, perhaps saying why first
            raise _last_word(conns[k]) or _lost(procs[k]) from None
        given += 1

    note = Timeline(timeline, -1)  # the parent's own events: worker -1
    try:
        note("pool")
        with sigint_blocked_for_children():
            for p in procs:
                p.start()
        note("started")
        for _, child in pipes:
            child.close()  # the processes hold their ends: EOF here means one has gone
        by_conn = {conn: k for k, conn in enumerate(conns)}
        open_conns = set(conns)
        while finished < workers:
            for conn in connection.wait(list(open_conns)):
                k = by_conn[conn]
                try:
                    kind, value = conn.recv()
                except (EOFError, OSError):  # its process has ended without saying "done"
                    raise _lost(procs[k]) from None
                if kind == "frames":
                    on_frames(value)
                    give(k)
                elif kind == "renderer":  # its first chunk only once its renderer is the dataset's
                    pin(value)
                    renderer = value
                    give(k)
                elif kind == "done":
                    finished += 1
                    open_conns.discard(conn)
                elif kind == "error":
                    raise _rebuild_error(value)
    finally:
        started = [p for p in procs if p.pid is not None]
        if finished < workers:  # stopped early: an error, a lost worker, or Ctrl-C
            for p in started:
                if p.is_alive():
                    p.terminate()
        for p in started:
            p.join()
        for parent, child in pipes:
            parent.close()
            child.close()
        if finished < workers:
            for p in started:  # a worker stopped mid-write leaves its temporary file
                for tmp in Path(out).glob(f"*/.*.tmp-{p.pid}"):
                    tmp.unlink(missing_ok=True)
    return renderer


def _last_word(conn) -> Exception | None:
    """The error a process that has gone sent before it went, if any (read from what is left in its pipe)."""
    try:
        while conn.poll():
            kind, value = conn.recv()
            if kind == "error":
                return _rebuild_error(value)
    except (EOFError, OSError):
        pass
    return None


def _lost(proc) -> SeasynthError:
    proc.join(timeout=5.0)
    return SeasynthError(f"a local worker stopped before finishing its frames (exit code {proc.exitcode})")


def _ignore_sigint() -> None:
    """In a pool worker (started with SIGINT blocked): ignore it from now on; a pending one is dropped."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _pool_main(payload: str, out: str, conn, platform: str, gpus: GpuChoice | None, k: int, pinned: str | None,
               env: dict[str, str], variants: str | None, timeline: str | None) -> None:
    _ignore_sigint()
    os.environ.clear()
    os.environ.update(env)  # before OpenGL is imported: it reads PYOPENGL_PLATFORM once
    note = Timeline(timeline, k)
    note("start")
    spec = DatasetSpec.model_validate_json(payload)
    try:  # platform_for_worker lists the EGL devices: here, in the render process, never in the parent
        with RenderSession(platform=platform_for_worker(platform, gpus, k), variant_folder=variants) as session:
            note("renderer")
            if pinned is not None and session.renderer_name != pinned:  # checked here: workers write frames
                raise OutputError(wrong_renderer(out, pinned, session.renderer_name))
            conn.send(("renderer", session.renderer_name))
            while (chunk := conn.recv()) is not None:
                for i in chunk:
                    write_frame(Path(out), session.frame_files(spec, i, mark=note.stage(i)))
                    note("written", i)
                conn.send(("frames", len(chunk)))
    except BaseException as err:  # report every failure to the parent, which decides
        with contextlib.suppress(OSError):  # the parent may be gone (it stops its workers on its way out)
            conn.send(("error", (type(err).__module__, type(err).__qualname__, str(err))))
        return
    conn.send(("done", None))


class Timeline:
    """Where a render process's time goes, for benchmarks (`seasynth generate --timeline FILE`): each process
    appends a JSON line per event (its start, its renderer open, each stage of its first frames, each frame
    written) with the wall-clock time; the parent (worker -1) notes when it asked for the processes. A no-op with no
    file. The command checks the file can be written before it starts; a write failing later (a full disk) is
    dropped rather than stopping a frame."""

    STAGED_FRAMES = 2  # frames of each process whose stages are noted

    def __init__(self, path: str | None, worker: int) -> None:
        self.path, self.worker, self.frames = path, worker, 0

    def __call__(self, event: str, frame: int | None = None) -> None:
        if self.path is None:
            return
        import json
        import time

        line = json.dumps({"t": time.time(), "pid": os.getpid(), "worker": self.worker, "event": event,
                           "frame": frame}) + "\n"
        with contextlib.suppress(OSError), open(self.path, "a", encoding="utf-8") as f:
            f.write(line)

    def stage(self, frame: int):
        """frame_files' `mark` for `frame`: its stages noted for the process's first STAGED_FRAMES frames."""
        self.frames += 1
        if self.path is None or self.frames > self.STAGED_FRAMES:
            return None
        return lambda name: self(name, frame)


def _rebuild_error(value: tuple[str, str, str]) -> Exception:
    module, name, message = value
    cls = getattr(errors, name, None) if module == errors.__name__ else None
    if cls is None:
        cls = SceneError if name == "SceneError" else SeasynthError
        message = message if cls is SceneError else f"{name}: {message}"
    return cls(message)
