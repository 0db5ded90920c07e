"""Procedural terrain variants shared by the render processes of one run through a folder.

Each process keeps the variants it has used (seasynth.worker.scene.assets.terrain's own cache), but every process of a run used to
build every variant it met: a seabed of 192x192 cells takes ~100 ms to build and to take the normals of (a 16-core
H100 host, 1280x720), so 24 processes each building the example's 30 spent ~70 CPU-seconds of a 20-second run on
the same 30 meshes. With a folder, the first process to need a variant writes it (vertices, faces, colours,
normals, heights: the arrays every frame reads, so frames are byte-identical either way) and the others read it in
a few milliseconds. Files are written whole and renamed into place; one that cannot be read is built again.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path

import numpy as np
import trimesh

from seasynth import service
from seasynth.worker.scene.assets import freeze
from seasynth.worker.scene.assets.terrain import Terrain, procedural_terrain
from seasynth.worker.scene.disk_cache import load_npz, share_in, store_npz

KEEP = 32  # variants kept in memory, as procedural_terrain's own cache


class VariantCache:
    """procedural_terrain through a folder shared with other processes (None: this process's cache only)."""

    def __init__(self, folder: Path | str | None) -> None:
        self.folder = None if folder is None else Path(folder)
        share_in(self.folder)  # procedural texture sets and solved water columns go through the same folder
        self._mem: OrderedDict[tuple, Terrain] = OrderedDict()
        self.built = self.read = 0  # for tests and benchmarks

    def terrain(self, style: str, variant: int, size_m: float, cells: int, relief_m: float) -> Terrain:
        if self.folder is None:
            return procedural_terrain(style, variant, size_m, cells, relief_m)
        args = (style, int(variant), float(size_m), int(cells), float(relief_m))
        got = self._mem.get(args)
        if got is None:
            path = self.folder / f"terrain-{_digest(args)}.npz"
            got = _load(path)
            if got is None:
                got = procedural_terrain(*args)
                _store(path, got)
                self.built += 1
            else:
                self.read += 1
            self._mem[args] = got
            while len(self._mem) > KEEP:
                self._mem.popitem(last=False)
        self._mem.move_to_end(args)
        return got


def _digest(args: tuple) -> str:
    return hashlib.sha256(repr((service.__version__, args)).encode()).hexdigest()[:32]


def _store(path: Path, t: Terrain) -> None:
    m = t.mesh
    store_npz(path, {"key": np.array(t.key), "extent": np.array(t.extent, dtype=np.float64), "heights": t.heights,
                     "vertices": np.asarray(m.vertices), "faces": np.asarray(m.faces),
                     "colours": np.asarray(m.visual.vertex_colors), "normals": np.asarray(m.vertex_normals)})


def _load(path: Path) -> Terrain | None:
    """The variant stored at path; None where there is none or it cannot be read whole (files are renamed into
    place whole, so that is a damaged one: it is built again)."""
    got = load_npz(path, lambda a: (trimesh.Trimesh(vertices=a["vertices"], faces=a["faces"],
                                                    vertex_colors=a["colours"], vertex_normals=a["normals"],
                                                    process=False),
                                    a["heights"], str(a["key"]), tuple(a["extent"].tolist())))
    if got is None:
        return None
    mesh, heights, key, extent = got
    heights.flags.writeable = False
    return Terrain(key=key, mesh=freeze(mesh), heights=heights, extent=extent, lookup=heights)
