"""Meshes the scene sampler places: procedural kinds (urchins, distractors, marine animals and litter), user files,
and their shared types."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from seasynth.service.errors import AssetError

if TYPE_CHECKING:
    import numpy as np
    import trimesh

    from seasynth.worker.render import Material

__all__ = ["Asset", "AssetError", "UserSurface", "file_identity", "freeze", "read_source"]


@dataclass(frozen=True, eq=False)
class UserSurface:
    """The per-pixel materials of a user mesh (seasynth.worker.scene.assets.surfaces), aligned with its Asset.mesh."""

    uv: np.ndarray  # (n, 2) float32 texture coordinates of the mesh's vertices, (0, 0) the image's top-left; 0 on
    # faces of no material
    # (first face, face count, material or None: vertex colours only) ranges covering the faces in order, a
    # material's faces in one range (seasynth.worker.render.Mesh.groups)
    groups: tuple[tuple[int, int, Material | None], ...]


@dataclass(frozen=True, eq=False)
class Asset:
    """One placeable mesh: metres, +z up, base at z = 0, bounding box centred on x, y = 0 (a procedural fish: its
    whole bounding box centred on 0, nose along +x, for the water column).

    `mesh` is shared through per-process caches: its vertex, face and colour arrays are read-only
    and callers must copy it (`mesh.copy()`) before changing anything else on it.
    """

    key: str  # cache / GPU-upload key, e.g. "procedural/urchin/3" or "file/<sha256>"
    mesh: trimesh.Trimesh  # vertex colours: (n, 4) uint8 sRGB-encoded RGBA
    sha256: str | None  # hex digest of the source file; None for procedural assets
    source: str  # human description for metadata, e.g. "procedural:urchin#3" or a file name
    surface: UserSurface | None = None  # a user file's textures, drawn per pixel; None: vertex colours only


def freeze(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Mark the mesh's vertex, face and vertex-colour arrays read-only and return it."""
    mesh.vertices.flags.writeable = False
    mesh.faces.flags.writeable = False
    mesh.visual.vertex_colors.flags.writeable = False
    return mesh


def read_source(path: Path) -> bytes:
    """The bytes of a user file; `AssetError` naming the path if it is missing or unreadable."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise AssetError(f"{path}: file not found") from None
    except OSError as exc:
        raise AssetError(f"{path}: cannot read file ({exc.strerror or exc})") from exc


def file_identity(path: Path) -> tuple[Path, int, int]:
    """(resolved path, mtime in ns, size in bytes) of a user file; `AssetError` if it is missing."""
    try:
        resolved = Path(path).resolve()
        stat = resolved.stat()
    except FileNotFoundError:
        raise AssetError(f"{path}: file not found") from None
    except OSError as exc:
        raise AssetError(f"{path}: cannot read file ({exc.strerror or exc})") from exc
    return resolved, stat.st_mtime_ns, stat.st_size
