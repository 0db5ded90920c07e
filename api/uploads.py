"""Uploaded files: their formats, what each spec field needs, and the checks that a mesh loads and an image decodes.

The checks use trimesh and Pillow (pure Python plus NumPy; no OpenGL), imported when an upload arrives.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from service.errors import AssetError, SeasynthError

MESH, IMAGE = "mesh", "image"
ARTICLED = {MESH: "a mesh", IMAGE: "an image"}

# Suffix -> (format, kind). The format is what workers load the file as (from the stored name's suffix).
FORMATS: dict[str, tuple[str, str]] = {
    ".glb": ("glb", MESH),
    ".obj": ("obj", MESH),
    ".ply": ("ply", MESH),
    ".stl": ("stl", MESH),
    ".png": ("png", IMAGE),
    ".jpg": ("jpeg", IMAGE),
    ".jpeg": ("jpeg", IMAGE),
}
# Decoding a texture holds all its pixels; a few bytes of PNG can declare billions of them.
MAX_TEXTURE_PIXELS = 8192 * 8192


@dataclass(frozen=True)
class FileFormat:
    format: str  # glb, obj, ply, stl, png or jpeg
    kind: str  # mesh or image

    def __str__(self) -> str:  # "a mesh (ply)", "an image (png)"
        return f"{ARTICLED[self.kind]} ({self.format})"


class ValidatorMissing(SeasynthError):
    """The API image lacks the package that checks uploads (a deployment fault, answered 500)."""


def format_of(filename: str) -> FileFormat | None:
    """The format a file name's suffix says, or None for a suffix uploads do not take."""
    got = FORMATS.get(Path(filename).suffix.lower())
    return None if got is None else FileFormat(*got)


def field_kind(field: str) -> str:
    """What a spec field that names a file needs: an image for terrain.texture, a mesh everywhere else."""
    return IMAGE if field == "terrain.texture" else MESH


def validate(path: Path, fmt: FileFormat, name: str) -> None:
    """AssetError naming `name` unless the file at `path` loads as `fmt`: a mesh with triangles and finite
    vertices, or an image that decodes whole."""
    if fmt.kind == MESH:
        _check_mesh(path, fmt.format, name)
    else:
        _check_image(path, name)


def _check_mesh(path: Path, file_type: str, name: str) -> None:
    try:
        import numpy as np
        import trimesh
    except ImportError as err:
        raise ValidatorMissing(f"checking mesh uploads needs trimesh in the API's environment ({err})") from err
    try:
        with open(path, "rb") as f:
            # As the workers read it (worker/assets/user.py): every part with triangles, transforms applied.
            scene = trimesh.load_scene(file_obj=f, file_type=file_type)
            parts = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except Exception as err:  # any parser failure means a bad file: answered 422 naming it
        raise AssetError(f"{name}: not a valid {file_type} mesh ({type(err).__name__}: {err})") from err
    if not parts:
        raise AssetError(f"{name}: the {file_type} mesh has no triangles")
    if not all(np.isfinite(np.asarray(g.vertices)).all() for g in parts):
        raise AssetError(f"{name}: the {file_type} mesh has vertices that are NaN or infinite")


def _check_image(path: Path, name: str) -> None:
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError as err:
        raise ValidatorMissing(f"checking image uploads needs Pillow in the API's environment ({err})") from err
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as image:
                w, h = image.size
                if w * h > MAX_TEXTURE_PIXELS:
                    raise AssetError(f"{name}: {w}x{h} pixels is over the limit of {MAX_TEXTURE_PIXELS} pixels "
                                     "for a texture")
                image.load()  # decodes every pixel: a truncated or corrupt file fails here
    except AssetError:
        raise
    except UnidentifiedImageError:  # its message names the server's temporary file
        raise AssetError(f"{name}: not an image Pillow can read (PNG or JPEG)") from None
    except Exception as err:
        raise AssetError(f"{name}: cannot decode as an image ({type(err).__name__}: {err})") from err
    if w == 0 or h == 0:
        raise AssetError(f"{name}: the image is empty")
