"""The export folder: atomic writes (temporary name, then rename), placing image files, and its record."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from seasynth.service.errors import ExportError
from seasynth.service.files import TMP_GLOB, atomic_path, tmp_name  # noqa: F401 (TMP_GLOB, tmp_name: for the exporters)

EXPORT_RECORD = "seasynth-export.json"  # says which format and whether the export is finished


@contextlib.contextmanager
def atomic_writer(path: Path) -> Iterator[BinaryIO]:
    """A binary file that appears at `path` whole when the block ends, and not at all if it raises."""
    make_dirs(path.parent)
    with atomic_path(path, ExportError) as tmp, open(tmp, "wb") as f:
        yield f


def write_atomic(path: Path, data: bytes) -> None:
    with atomic_writer(path) as f:
        f.write(data)


def place_file(src: Path, dest: Path) -> None:
    """Make `dest` a file with `src`'s bytes: a hard link where the filesystem allows, else a copy."""
    try:
        if dest.exists() and os.path.samefile(src, dest):  # linked by an earlier run
            return
    except OSError:
        pass  # not comparable: replace it below
    tmp = tmp_name(dest)
    try:
        tmp.unlink(missing_ok=True)
        try:
            os.link(src, tmp)
        except OSError:  # another filesystem, or one without hard links
            shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise ExportError(f"{dest}: cannot write a copy of {src} ({err.strerror or err})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def make_dirs(*paths: Path) -> None:
    for path in paths:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ExportError(f"{path}: cannot create folder ({err.strerror or err})") from None


def json_bytes(value: object) -> bytes:
    return (json.dumps(value, indent=1, sort_keys=True) + "\n").encode()


def check_export_folder(out: Path, fmt: str) -> None:
    """ExportError unless `out` may receive a `fmt` export: absent, empty, or holding an earlier export of the same
    format (which the export replaces). Reads only, so a command can ask before it starts work."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: exists and is not a folder")
    if not out.exists():
        return
    record = out / EXPORT_RECORD
    try:
        empty = next(out.iterdir(), None) is None
    except OSError as err:
        raise ExportError(f"{out}: cannot list the export folder ({err.strerror or err})") from None
    if empty:
        return
    if not record.is_file():
        raise ExportError(f"{out}: folder is not empty and holds no seasynth export ({EXPORT_RECORD}); "
                          "choose a new or empty folder")
    try:
        old = json.loads(record.read_text())
    except (OSError, ValueError) as err:
        raise ExportError(f"{record}: unreadable ({err})") from None
    if not isinstance(old, dict) or old.get("format") != fmt:
        got = old.get("format") if isinstance(old, dict) else None
        raise ExportError(f"{out}: holds a {got!r} export, not {fmt!r}; choose another folder")


def open_export_folder(out: Path, fmt: str) -> None:
    """Check `out` may receive a `fmt` export (check_export_folder), mark it unfinished, and delete temporary files
    a crash left."""
    out = Path(out)
    check_export_folder(out, fmt)
    make_dirs(out)
    write_atomic(out / EXPORT_RECORD, json_bytes({"format": fmt, "state": "incomplete"}))
    try:
        for p in out.rglob(TMP_GLOB):
            p.unlink()
    except OSError as err:
        raise ExportError(f"{out}: cannot remove temporary files of an earlier run ({err.strerror or err})") from None
