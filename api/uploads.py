"""Uploaded files: their formats, what each spec field needs, and the checks that a mesh loads and an image decodes.

The checks use trimesh and Pillow (pure Python plus NumPy; no OpenGL). A mesh is loaded in a child process with a
memory budget (seasynth.api.mesh_check), so a mesh too large to load is refused (413) instead of taking the API's memory.
A .zip is a mesh too: a glTF or OBJ with the files it names, checked and extracted in that child process
(seasynth.service.archives) as workers extract it, then loaded the same way; a GLB's embedded images and an archive's
images are held to the pixel budgets (seasynth.service.textures) before anything decodes them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

from seasynth.service.errors import AssetError, LimitExceeded, SeasynthError
from seasynth.service.settings import MAX_IMAGE_PIXELS, UPLOAD_CHECK_MEMORY_MIB

MESH, IMAGE = "mesh", "image"
ARTICLED = {MESH: "a mesh", IMAGE: "an image"}

# Suffix -> (format, kind). The format is what workers load the file as (from the stored name's suffix).
FORMATS: dict[str, tuple[str, str]] = {
    ".glb": ("glb", MESH),
    ".obj": ("obj", MESH),
    ".ply": ("ply", MESH),
    ".stl": ("stl", MESH),
    ".zip": ("zip", MESH),  # a textured glTF or OBJ with its files (seasynth.service.archives); stored as a .zip
    ".png": ("png", IMAGE),
    ".jpg": ("jpeg", IMAGE),
    ".jpeg": ("jpeg", IMAGE),
}
MESH_CHECK_TIMEOUT_S = 120
_MESH_CHECKS = threading.BoundedSemaphore(1)


@dataclass(frozen=True)
class FileFormat:
    format: str  # glb, obj, ply, stl, zip, png or jpeg
    kind: str  # mesh or image

    def __str__(self) -> str:  # "a mesh (ply)", "an image (png)"
        return f"{ARTICLED[self.kind]} ({self.format})"


class ValidatorMissing(SeasynthError):
    """The API image lacks the package that checks uploads (a deployment fault, answered 500)."""


def format_of(filename: str) -> FileFormat | None:
    """The format a file name's suffix says, or None for a suffix uploads do not take."""
    got = FORMATS.get(Path(filename).suffix.lower())
    return None if got is None else FileFormat(*got)


IMAGE_FIELDS = ("terrain.texture", "terrain.normal_map", "terrain.height_map")


def field_kind(field: str) -> str:
    """What a spec field that names a file needs: an image for the terrain's texture set, a mesh everywhere else."""
    return IMAGE if field in IMAGE_FIELDS else MESH


def validate(path: Path, fmt: FileFormat, name: str, mesh_budget_mib: int = UPLOAD_CHECK_MEMORY_MIB,
             thumbnail: Path | None = None) -> str | None:
    """AssetError naming `name` unless the file at `path` loads as `fmt`: a mesh with triangles and finite
    vertices (loaded within `mesh_budget_mib` of memory, else LimitExceeded), or an image that decodes whole.

    With `thumbnail`, a valid mesh's picture (seasynth.api.mesh_thumbnail) is written there as PNG in the same
    load; the answer is then None, or why it could not be drawn (the mesh is valid all the same)."""
    if fmt.kind == MESH:
        return _check_mesh(path, fmt.format, name, mesh_budget_mib, thumbnail)
    _check_image(path, name)
    return None


def _check_mesh(path: Path, file_type: str, name: str, budget_mib: int, thumbnail: Path | None) -> str | None:
    """Load the mesh as the workers do, in a child process (seasynth.api.mesh_check) within `budget_mib` of memory;
    with `thumbnail`, draw its picture there. Returns why no picture was drawn, if asked for one and it failed."""
    # The script by its path. Besides NumPy, trimesh and Pillow it imports seasynth.service (archives, textures) for
    # .zip and .glb uploads. An archive is extracted into `work`, removed here even if the child is killed for time.
    script = Path(__file__).with_name("mesh_check.py")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    try:
        with _MESH_CHECKS, tempfile.TemporaryDirectory(prefix="seasynth-check-") as work:
            # One at a time: the API's memory holds one budget beside its own (deploy/core/api.yaml).
            cmd = [sys.executable, str(script), str(path), file_type, str(budget_mib), name, work,
                   *([] if thumbnail is None else [str(thumbnail)])]
            run = subprocess.run(cmd, capture_output=True, text=True, timeout=MESH_CHECK_TIMEOUT_S, env=env)
        answer = json.loads(run.stdout.strip().splitlines()[-1]) if run.stdout.strip() else {}
    except subprocess.TimeoutExpired:
        raise LimitExceeded(f"{name}: the {file_type} mesh did not load within {MESH_CHECK_TIMEOUT_S} s; "
                            "upload a smaller one (decimate it, or split it into assets)") from None
    except (OSError, ValueError) as err:
        raise ValidatorMissing(f"checking mesh uploads failed to run ({err})") from err
    if answer.get("memory") or (not answer and run.returncode < 0):  # MemoryError, or killed for memory
        raise LimitExceeded(f"{name}: loading the {file_type} mesh needs more than {budget_mib} MiB "
                            "(SEASYNTH_UPLOAD_CHECK_MEMORY_MIB); upload a smaller one (decimate it, or split it "
                            "into assets)")
    if "error" in answer:  # names the upload (and an archive's member) already
        raise AssetError(answer["error"])
    if not answer.get("ok"):
        if "No module named" in run.stderr:
            raise ValidatorMissing(f"checking mesh uploads needs trimesh in the API's environment "
                                   f"({run.stderr.strip().splitlines()[-1]})")
        raise ValidatorMissing(f"checking {name} failed: exit code {run.returncode}: {run.stderr.strip()[-500:]}")
    return answer.get("thumbnail_error")


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
                if w * h > MAX_IMAGE_PIXELS:
                    raise AssetError(f"{name}: {w}x{h} pixels is over the limit of {MAX_IMAGE_PIXELS} pixels "
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
