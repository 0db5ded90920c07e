"""Local generation (the embedded default): frames rendered by K local processes into a KITTI folder."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from seasynth import service
from seasynth.service.errors import OutputError
from seasynth.service.files import TMP_GLOB, write_atomic
from seasynth.service.gpus import GpuChoice
from seasynth.service.spec.dataset import DatasetSpec, spec_digest
from seasynth.worker.local.capacity import render_processes
from seasynth.worker.export import GENERATED_EXPORTS
from seasynth.worker.frame.function import RenderSession, frame_paths

RECORD = "seasynth.json"  # the dataset record: spec, code version, and whether every frame is written
OUTPUT_DIRS = ("image_2", "label_2", "calib", "meta", "depth", "instance", "clean", "range",
               "fls", "fls_fan", "fls_label", "sss", "sss_label", "nav")  # from fls: seasynth.worker.sensors.outputs
CHUNK = 4  # frames a local worker takes at a time: small enough to balance, large enough to amortise IPC

Mode = Literal["new", "resume", "overwrite"]


@dataclass(frozen=True)
class GenerateReport:
    frames_total: int
    frames_rendered: int
    frames_skipped: int
    renderer: str


def write_frame(out: Path, files: dict[str, bytes]) -> None:
    for rel, data in files.items():
        write_atomic(out / rel, data)


def prepare_output(out: Path, spec: DatasetSpec, mode: Mode, files: dict[str, str] | None = None) -> None:
    """Check and set up the output folder; leave it marked incomplete until every frame is written.

    `files` maps the spec field naming each local user file to its sha256 (see `check_assets`). Resuming
    refuses a folder whose record names another spec, code version or user file content.
    """
    files = {} if files is None else files
    renderer = None
    try:
        out.mkdir(parents=True, exist_ok=True)
        existing = [p for p in out.iterdir()]
    except OSError as err:
        raise OutputError(f"{out}: cannot create or list the output folder ({err.strerror or err})") from None
    record_path = out / RECORD
    if existing and mode == "new":
        raise OutputError(f"{out}: folder is not empty; pass --resume to complete it or --overwrite to replace it")
    if mode == "resume" and record_path.exists():
        old = read_record(out)
        if old.get("spec_sha256") != spec_digest(spec):
            raise OutputError(
                f"{out}: holds a dataset of another spec (spec_sha256 {old.get('spec_sha256')}); "
                "use --overwrite or another folder"
            )
        differences = record_differences(old, spec, files)
        if differences:
            raise OutputError(f"{out}: cannot resume, its frames would not match: {'; '.join(differences)}; "
                              "use --overwrite to start again, or another folder")
        renderer = old.get("renderer")
    elif mode == "resume" and existing:
        raise OutputError(f"{out}: is not a seasynth dataset (no {RECORD}); use --overwrite or another folder")
    try:
        if mode == "overwrite":
            for name in (*OUTPUT_DIRS, RECORD, GENERATED_EXPORTS):
                target = out / name
                if target.is_dir():
                    shutil.rmtree(target)
                elif target.exists():
                    target.unlink()
        for p in (*out.glob(TMP_GLOB), *out.glob(f"*/{TMP_GLOB}")):  # left by an interrupted run (the record's too)
            p.unlink()
        for rel in frame_paths(spec, 0):
            (out / rel).parent.mkdir(exist_ok=True)
    except OSError as err:
        raise OutputError(f"{out}: cannot write the output folder ({err.strerror or err})") from None
    write_record(out, spec, complete=False, renderer=renderer, files=files)


def record_differences(old: dict, spec: DatasetSpec, files: dict[str, str]) -> list[str]:
    """What in a dataset record (of the same spec) differs from this run: code version and user file content.

    Keys an older record lacks are not compared. The renderer is compared once it is known (`render_frames`).
    """
    found = []
    version = old.get("code_version")
    if version is not None and version != service.__version__:
        found.append(f"it was started by code version {version}, this is {service.__version__}")
    recorded = old.get("user_files")
    if recorded is not None:
        paths = {field: ref.path for field, ref in spec.file_refs()}
        for field in sorted(set(recorded) | set(files)):
            if recorded.get(field) != files.get(field):
                found.append(f"{field} ({paths.get(field)}) has sha256 {files.get(field)}, "
                             f"the dataset was started with {recorded.get(field)}")
    return found


def read_record(out: Path) -> dict:
    """The dataset record in `out`; `OutputError` naming it if it cannot be read."""
    path = out / RECORD
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise OutputError(f"{path}: unreadable dataset record ({err})") from None


def write_record(out: Path, spec: DatasetSpec, complete: bool, renderer: str | None,
                 files: dict[str, str]) -> None:
    """The dataset record: what its frames depend on (spec, code version, GL renderer, user files' sha256)."""
    record = {
        "state": "complete" if complete else "incomplete",
        "frames": spec.frames,
        "seed": spec.seed,
        "code_version": service.__version__,
        "renderer": renderer,  # null until a frame is rendered
        "user_files": files,  # spec field -> sha256 of each local user file
        "spec_sha256": spec_digest(spec),
        "spec": spec.model_dump(mode="json"),
    }
    write_atomic(out / RECORD, (json.dumps(record, indent=1, sort_keys=True) + "\n").encode())


def pending_frames(out: Path, spec: DatasetSpec, frames: Iterable[int]) -> list[int]:
    """Frames not yet complete on disk (a frame is complete when every one of its files exists)."""
    return [i for i in frames if not all((out / rel).exists() for rel in frame_paths(spec, i))]


def check_assets(spec: DatasetSpec) -> dict[str, str]:
    """Fail before any rendering if a user mesh or texture named by the spec cannot be used.

    Returns the sha256 of each local user file by the spec field that names it.
    """
    from seasynth.worker.scene.assets.user import load_user_asset, load_user_terrain, load_user_texture

    files = {}
    for field, ref in spec.file_refs():
        if ref.path is None:
            continue
        if field == "terrain.texture":
            # Decoded, not only read: a bad image fails here, not at a frame.
            files[field] = load_user_texture(Path(ref.path)).sha256
        elif field == "terrain.mesh":
            files[field] = load_user_terrain(Path(ref.path)).sha256
        else:
            files[field] = load_user_asset(Path(ref.path)).sha256
    return files


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


def wrong_renderer(out: Path | str, pinned: str, ours: str) -> str:
    return (f"{out}: cannot resume, its frames would not match: they were rendered with {pinned!r}, this machine "
            f"renders with {ours!r}; use --overwrite to start again, or resume where that renderer is")


def reproduce(spec: DatasetSpec, index: int, out: Path, platform: str = "egl") -> list[str]:
    """Write frame `index` at the same relative paths `generate` uses; returns those paths."""
    if not 0 <= index < spec.frames:
        raise OutputError(f"frame {index} is outside the dataset (frames 0..{spec.frames - 1})")
    check_assets(spec)
    with RenderSession(platform=platform) as session:
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
        from seasynth.worker.render.devices import platform_for_worker

        with RenderSession(platform=platform_for_worker(platform, gpus, 0)) as session:
            pin(session.renderer_name)
            for i in todo:
                write_frame(out, session.frame_files(spec, i))
                on_frames(1)
            return session.renderer_name
    from seasynth.worker.local.pool import run_pool

    return run_pool(spec, out, todo, workers, on_frames, platform, gpus, pinned, pin,
                    None if timeline is None else str(timeline))
