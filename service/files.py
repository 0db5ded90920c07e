"""Files written whole: through a hidden temporary name in the same folder, then renamed, so that a reader sees the
old file or the whole new one, never a part, and an interrupted write leaves no temporary file."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from seasynth.service.errors import OutputError, SeasynthError

TMP_GLOB = ".*.tmp-*"  # what tmp_name makes, for sweeping what a killed process left


def tmp_name(path: Path) -> Path:
    """Where `path` is written before it is renamed into place (hidden; this process's id keeps runs apart)."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


@contextlib.contextmanager
def atomic_path(path: Path, error: type[SeasynthError] = OutputError) -> Iterator[Path]:
    """The temporary path to write `path`'s content to: renamed onto `path` when the block ends, removed if it
    raises. An OSError (the block's or the rename's) becomes `error` naming `path`."""
    tmp = tmp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as err:
        # A folder that turned read-only refuses the unlink too: the error to report is the write's (the next run's
        # sweep of TMP_GLOB removes the file).
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise error(f"{path}: cannot write ({err.strerror or err})") from None
    except BaseException:  # Ctrl-C or an error mid-write
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def write_atomic(path: Path, data: bytes, error: type[SeasynthError] = OutputError) -> None:
    """`data` into `path` whole (atomic_path)."""
    with atomic_path(path, error) as tmp:
        tmp.write_bytes(data)
