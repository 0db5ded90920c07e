"""A local dataset's folder: its record (seasynth.json: spec, code version, renderer, user files, whether every
frame is written), setting it up for a new, resumed or overwritten run, and writing a frame's files into it."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

from seasynth import service
from seasynth.service.errors import OutputError
from seasynth.service.files import TMP_GLOB, write_atomic
from seasynth.service.spec.dataset import DatasetSpec, spec_digest
from seasynth.worker.export import GENERATED_EXPORTS
from seasynth.worker.frame.function import frame_paths

RECORD = "seasynth.json"  # the dataset record: spec, code version, and whether every frame is written
OUTPUT_DIRS = ("image_2", "label_2", "calib", "meta", "depth", "instance", "semantic", "clean", "range",
               "fls", "fls_fan", "fls_label", "sss", "sss_label", "nav")  # from fls: seasynth.worker.sensors.outputs


Mode = Literal["new", "resume", "overwrite"]


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


def wrong_renderer(out: Path | str, pinned: str, ours: str) -> str:
    return (f"{out}: cannot resume, its frames would not match: they were rendered with {pinned!r}, this machine "
            f"renders with {ours!r}; use --overwrite to start again, or resume where that renderer is")
