"""Zipped textured meshes on a worker: each archive extracted once into a folder keyed by its sha256, and the mesh
inside it handed to the mesh loader (seasynth.worker.scene.assets.user)."""

from __future__ import annotations

import functools
import hashlib
import tempfile
from pathlib import Path

from seasynth.service.archives import safe_extract
from seasynth.service.errors import AssetError
from seasynth.worker.scene.assets import file_identity

CACHE_FOLDER = "seasynth-archives"  # under the system's temporary folder


def mesh_in_archive(path: Path) -> Path:
    """The path of the one mesh (.gltf, .glb or .obj) inside the zip at `path`, extracted with its files into
    `tempfile.gettempdir()/seasynth-archives/<sha256 of the zip>` (checked as the API checks uploads, then renamed
    into place whole, so processes sharing the folder never see half an extraction); `AssetError` names the
    archive and the member at fault."""
    resolved, mtime_ns, size = file_identity(path)
    sha256 = _sha256(resolved, mtime_ns, size)
    return safe_extract(resolved, Path(tempfile.gettempdir()) / CACHE_FOLDER / sha256, name=Path(path).name)


@functools.lru_cache(maxsize=256)
def _sha256(path: Path, mtime_ns: int, size: int) -> str:
    """Hex sha256 of a file, once per process for each (path, mtime, size)."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                digest.update(chunk)
    except OSError as exc:
        raise AssetError(f"{path}: cannot read file ({exc.strerror or exc})") from exc
    return digest.hexdigest()
