"""Terrain variants shared by the render processes of a run through a folder (seasynth.worker.scene.variant_cache)."""

from __future__ import annotations

import numpy as np
import pytest

from seasynth.worker.frame.function import to_render_mesh
from seasynth.worker.scene.assets.terrain import procedural_terrain
from seasynth.worker.scene.variant_cache import VariantCache

ARGS = ("pebbles", 3, 4.0, 24, 0.3)


def same_terrain(a, b) -> None:
    """Every array a frame reads of a terrain, bit for bit, and the render mesh made of it."""
    assert a.key == b.key and a.extent == b.extent
    for name in ("vertices", "faces", "vertex_normals"):
        x, y = np.asarray(getattr(a.mesh, name)), np.asarray(getattr(b.mesh, name))
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert np.array_equal(a.mesh.visual.vertex_colors, b.mesh.visual.vertex_colors)
    assert a.heights.dtype == b.heights.dtype and np.array_equal(a.heights, b.heights)
    assert np.array_equal(a.height_at(np.array([[0.3, -1.1]])), b.height_at(np.array([[0.3, -1.1]])))
    ra, rb = to_render_mesh(a.key, a.mesh), to_render_mesh(b.key, b.mesh)
    for name in ("vertices", "normals", "albedo", "faces", "centre"):
        assert np.array_equal(getattr(ra, name), getattr(rb, name)), name
    assert ra.radius == rb.radius


def test_the_first_process_builds_a_variant_and_the_next_reads_the_same_arrays(tmp_path):
    first, second = VariantCache(tmp_path), VariantCache(tmp_path)
    built = first.terrain(*ARGS)
    got = second.terrain(*ARGS)
    assert (first.built, first.read, second.built, second.read) == (1, 0, 0, 1)
    same_terrain(got, procedural_terrain(*ARGS))
    same_terrain(got, built)
    assert not got.mesh.vertices.flags.writeable and not got.heights.flags.writeable  # shared, as built ones are
    assert second.terrain(*ARGS) is got  # then from memory
    assert [p.name.startswith(".") for p in tmp_path.iterdir()] == [False]  # one file, no temporary left


def test_other_arguments_are_other_variants(tmp_path):
    cache = VariantCache(tmp_path)
    keys = {cache.terrain(*ARGS).key, cache.terrain("pebbles", 4, 4.0, 24, 0.3).key,
            cache.terrain("pebbles", 3, 4.0, 24, 0.5).key, cache.terrain("sand", 3, 4.0, 24, 0.3).key}
    assert len(keys) == 4 and cache.built == 4 and len(list(tmp_path.iterdir())) == 4


@pytest.mark.parametrize("damage", ["truncated", "empty", "not-npz"])
def test_a_damaged_file_is_built_again_and_replaced(tmp_path, damage):
    VariantCache(tmp_path).terrain(*ARGS)
    (path,) = tmp_path.iterdir()
    data = path.read_bytes()
    path.write_bytes({"truncated": data[: len(data) // 2], "empty": b"", "not-npz": b"terrain"}[damage])
    again = VariantCache(tmp_path)
    same_terrain(again.terrain(*ARGS), procedural_terrain(*ARGS))
    assert (again.built, again.read) == (1, 0)
    later = VariantCache(tmp_path)
    later.terrain(*ARGS)
    assert (later.built, later.read) == (0, 1)


def test_an_unwritable_folder_costs_only_the_speed_up(tmp_path):
    blocked = tmp_path / "file-not-folder"
    blocked.write_text("")
    cache = VariantCache(blocked / "variants")
    same_terrain(cache.terrain(*ARGS), procedural_terrain(*ARGS))
    assert cache.built == 1


def test_without_a_folder_it_is_the_process_cache():
    assert VariantCache(None).terrain(*ARGS) is procedural_terrain(*ARGS)
