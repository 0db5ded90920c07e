"""Procedural texture sets shared by the render processes of one run through a folder, as terrain variants are
(seasynth.worker.scene.variant_cache): the first process to need a set writes its arrays (whole, renamed into
place) and the others read them, instead of every process building every set (about 0.1-0.3 s each at 512 texels;
the default example meets 32, so 16 processes spent ~100 CPU-seconds on the same sets). Frames are byte-identical
either way: the stored arrays are the built ones."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import numpy as np

from seasynth import service
from seasynth.worker.scene.assets.textures import TextureSet, texture_set
from seasynth.worker.scene.disk_cache import load_npz, shared_folder, store_npz


@functools.lru_cache(maxsize=64)
def shared_texture_set(family: str, variant: int, size: int) -> TextureSet:
    """texture_set(family, variant, size), read from the shared folder where another process stored it."""
    folder = shared_folder()
    if folder is None:
        return texture_set(family, variant, size)
    digest = hashlib.sha256(repr((service.__version__, family, int(variant), int(size))).encode()).hexdigest()[:32]
    path = folder / f"texture-{digest}.npz"
    got = _load(path)
    if got is None:
        got = texture_set(family, variant, size)
        _store(path, got)
    return got


def _store(path: Path, t: TextureSet) -> None:
    store_npz(path, {"key": np.array(t.key), "source": np.array(t.source), "gain": np.array(t.albedo_gain),
                     "tile_m": np.array(t.tile_m), "albedo": t.albedo, "normal": t.normal, "height_m": t.height_m})


def _load(path: Path) -> TextureSet | None:
    """The set stored at path; None where there is none or it cannot be read whole (then it is built again)."""
    t = load_npz(path, lambda a: TextureSet(key=str(a["key"]), albedo=a["albedo"], albedo_gain=float(a["gain"]),
                                            normal=a["normal"], height_m=a["height_m"], tile_m=float(a["tile_m"]),
                                            source=str(a["source"])))
    if t is not None:
        for array in (t.albedo, t.normal, t.height_m):
            array.flags.writeable = False
    return t
