"""The folder where procedural terrain variants and texture sets outlive a run.

Within a run the render processes already share what they build through a folder (variant_cache, texture_cache);
this puts that folder where the next run finds it: `$SEASYNTH_CACHE_DIR` (default `$XDG_CACHE_HOME/seasynth`, else
`~/.cache/seasynth`), in a subfolder named by a digest of this code (the package version and the bytes of every
module of `seasynth.service` and `seasynth.worker`), so no run reads arrays an older code built. The stored
arrays are the built ones, so frames are byte-identical with or without it. `SEASYNTH_CACHE_DIR` set to `off` (or
empty) keeps it to the run; a folder that cannot be made does the same. Of the subfolders of other code (about
100 MB each for the example), the KEEP_OTHERS used last are kept, and none unused for KEEP_DAYS.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import os
import shutil
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

import numpy as np

from seasynth import service, worker

ENV = "SEASYNTH_CACHE_DIR"
OFF = {"", "0", "off", "none", "false"}
KEEP_DAYS = 7.0
KEEP_OTHERS = 2
T = TypeVar("T")
_shared: list[Path | None] = [None]  # where this process shares what it builds (its RenderSession's folder), if anywhere


def share_in(folder: Path | str | None) -> None:
    """Share what this process builds (texture sets, solved water columns; terrain variants go through their
    VariantCache) through `folder` (None: build them in this process only)."""
    _shared[0] = None if folder is None else Path(folder)


def shared_folder() -> Path | None:
    return _shared[0]


def store_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write arrays to path whole: into a temporary file beside it, renamed into place (readers never see half a
    file; a write stopped by a signal leaves no part behind). A full or read-only disk costs the writer its
    speed-up, nothing more."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".part-", suffix=".npz")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
        tmp = None
    except OSError:
        pass
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                Path(tmp).unlink()


def load_npz(path: Path, make: Callable[[dict[str, np.ndarray]], T]) -> T | None:
    """make(the arrays stored at path); None where there is none or it cannot be read or made whole (files are
    renamed into place whole, so that is a damaged one: the caller builds it again)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return make({k: z[k] for k in z.files})
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def stored_once(path: Path, load: Callable[[Path], T | None], build: Callable[[], T],
                store: Callable[[Path, T], None]) -> T:
    """load(path), else build() and store it at path, with processes sharing the folder building it once: the
    builder holds an exclusive lock on `path`.lock (released by the system if it dies) while the others wait for
    it and then load what it stored. Where no lock can be made, each builds its own."""
    got = load(path)
    if got is not None:
        return got
    with _exclusive(path.with_name(path.name + ".lock")):
        got = load(path)  # another process may have stored it while this one waited
        if got is None:
            got = build()
            store(path, got)
    return got


@contextlib.contextmanager
def _exclusive(lock: Path):
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_CREAT | os.O_RDWR, 0o600)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def run_folder() -> contextlib.AbstractContextManager[str | None]:
    """The folder a run's render processes share what they build through: the cache folder (kept after the run)
    where it is on, else a new temporary folder (removed after it). Making the temporary folder may raise OSError."""
    lasting = cache_folder()
    if lasting is not None:
        return contextlib.nullcontext(str(lasting))
    return tempfile.TemporaryDirectory(prefix="seasynth-variants-", ignore_cleanup_errors=True)


def cache_folder() -> Path | None:
    """This code's folder of built variants and texture sets, made if absent; None where caching across runs is off
    or the folder cannot be made."""
    raw = os.environ.get(ENV)
    if raw is not None and raw.strip().lower() in OFF:
        return None
    try:
        base = Path(raw) if raw else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "seasynth"
        folder = base / f"variants-{code_digest()}"
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)  # in use: pruning goes by when a folder was last used
    except (OSError, RuntimeError):  # RuntimeError: no home folder to be found
        return None
    _prune(base, folder)
    return folder


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """The digest of this code: source_digest of the version and the `seasynth.service` and `seasynth.worker`
    packages (every module that builds or describes what the cache holds)."""
    return source_digest(service.__version__, [Path(p) for pkg in (service, worker) for p in pkg.__path__])


def source_digest(version: str, roots: Iterable[Path]) -> str:
    """sha256 (20 hex digits) of `version` and of every .py file under `roots`, each with its path in its root."""
    h = hashlib.sha256(version.encode() + b"\0")
    for k, root in enumerate(roots):
        for path in sorted(root.rglob("*.py")):
            h.update(f"{k}:{path.relative_to(root).as_posix()}".encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:20]


def _prune(base: Path, keep: Path) -> None:
    """Remove the subfolders of other code but the KEEP_OTHERS used last, and any unused for KEEP_DAYS."""
    cutoff = time.time() - KEEP_DAYS * 86400.0
    others = []
    for other in base.glob("variants-*"):
        try:
            if other != keep and other.is_dir():
                others.append((other.stat().st_mtime, other))
        except OSError:
            continue
    others.sort(reverse=True)
    for k, (used, other) in enumerate(others):
        if k >= KEEP_OTHERS or used < cutoff:
            shutil.rmtree(other, ignore_errors=True)
