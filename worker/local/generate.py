"""Local generation (the embedded default): frames rendered by K local processes into a KITTI folder."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from seasynth.service.errors import OutputError
from seasynth.service.gpus import GpuChoice
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.local.capacity import render_processes
from seasynth.worker.local.folder import (
    Mode,
    pending_frames,
    prepare_output,
    read_record,
    write_frame,
    write_record,
    wrong_renderer,
)
from seasynth.worker.local.pool import run_pool
from seasynth.worker.render.devices import platform_for_worker
from seasynth.worker.scene.assets.user import check_assets
from seasynth.worker.scene.disk_cache import cache_folder


@dataclass(frozen=True)
class GenerateReport:
    frames_total: int
    frames_rendered: int
    frames_skipped: int
    renderer: str


def generate(
    spec: DatasetSpec,
    out: Path,
    *,
    workers: int = 1,
    mode: Mode = "new",
    on_frames: Callable[[int], None] | None = None,
    platform: str = "egl",
    gpus: GpuChoice | None = None,
    timeline: Path | None = None,
) -> GenerateReport:
    """Render every frame of `spec` into `out`. Files are the same whatever `workers`, `gpus` or resuming."""
    todo = open_dataset(spec, out, mode)
    return render_frames(spec, out, todo, workers=workers, on_frames=on_frames, platform=platform, gpus=gpus,
                         timeline=timeline)


def auto_workers(frames_to_render: int, gpus: int = 0) -> int:
    """Render processes that fill this machine (seasynth.worker.local.capacity: one a core on a software renderer, 1.5 a core on
    `gpus` GPUs), at most one per frame to render, at least one."""
    return max(1, min(render_processes(gpus), frames_to_render))


def open_dataset(spec: DatasetSpec, out: Path, mode: Mode = "new") -> list[int]:
    """Check the spec's files and the output folder, mark the dataset incomplete; the frames still to render."""
    files = check_assets(spec)
    prepare_output(out, spec, mode, files)
    return pending_frames(out, spec, range(spec.frames))


def render_frames(
    spec: DatasetSpec,
    out: Path,
    todo: list[int],
    *,
    workers: int = 1,
    on_frames: Callable[[int], None] | None = None,
    platform: str = "egl",
    gpus: GpuChoice | None = None,
    timeline: Path | None = None,
) -> GenerateReport:
    """Render `todo` into an opened dataset folder, then mark the dataset complete. Render process k uses the
    k-th of the `gpus` devices, round robin (None: EGL's default device). timeline: with several processes, a file
    each notes its start-up and frames to (seasynth.worker.local.pool.Timeline), for benchmarks.

    The record pins the GL renderer of the first frame rendered; another renderer is refused before it writes.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    record = read_record(out)
    files, pinned = record.get("user_files", {}), record.get("renderer")

    def pin(renderer: str) -> None:
        nonlocal pinned
        if pinned is None:
            write_record(out, spec, complete=False, renderer=renderer, files=files)
            pinned = renderer
        elif renderer != pinned:
            raise OutputError(wrong_renderer(out, pinned, renderer))

    skipped = spec.frames - len(todo)
    renderer = _run(spec, out, todo, workers, on_frames or (lambda n: None), platform, gpus, pinned, pin, timeline)
    write_record(out, spec, complete=True, renderer=pinned, files=files)
    return GenerateReport(spec.frames, len(todo), skipped, renderer)


def reproduce(spec: DatasetSpec, index: int, out: Path, platform: str = "egl") -> list[str]:
    """Write frame `index` at the same relative paths `generate` uses; returns those paths."""
    if not 0 <= index < spec.frames:
        raise OutputError(f"frame {index} is outside the dataset (frames 0..{spec.frames - 1})")
    check_assets(spec)
    with RenderSession(platform=platform, variant_folder=cache_folder()) as session:
        files = session.frame_files(spec, index)
    for rel in files:
        try:
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"{out / rel}: cannot create folder ({err.strerror or err})") from None
    write_frame(out, files)
    return list(files)


def _run(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin, timeline=None) -> str:
    if not todo:
        return ""
    if workers == 1:
        with RenderSession(platform=platform_for_worker(platform, gpus, 0), variant_folder=cache_folder()) as session:
            pin(session.renderer_name)
            for i in todo:
                write_frame(out, session.frame_files(spec, i))
                on_frames(1)
            return session.renderer_name
    return run_pool(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin,
                    None if timeline is None else str(timeline))
