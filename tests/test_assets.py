"""Tests for procedural assets and user mesh loading."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import trimesh

from seasynth.worker.scene.assets import Asset, AssetError
from seasynth.worker.scene.assets.procedural import procedural_asset, stable_seed
from seasynth.worker.scene.assets.user import load_user_asset

KINDS = ["clam", "coral", "rock", "seaweed", "urchin"]  # the first five; the marine vocabulary: test_vocabulary.py
VARIANTS = range(6)
BUDGET = {"urchin": 6000, "rock": 3000, "coral": 3000, "seaweed": 3000, "clam": 3000}


def mesh_bytes(mesh: trimesh.Trimesh) -> bytes:
    return mesh.vertices.tobytes() + mesh.faces.tobytes() + mesh.visual.vertex_colors.tobytes()


def test_stable_seed_is_crc32_of_name() -> None:
    assert stable_seed("urchin") == 0x185DD0BA  # fixed forever: changing it changes every dataset
    assert stable_seed("urchin") != stable_seed("rock")


@pytest.mark.parametrize("kind", KINDS)
def test_same_variant_is_identical_and_variants_differ(kind: str) -> None:
    first = procedural_asset(kind, 3)
    procedural_asset.cache_clear()
    again = procedural_asset(kind, 3)
    assert again is not first and mesh_bytes(again.mesh) == mesh_bytes(first.mesh)
    assert mesh_bytes(procedural_asset(kind, 4).mesh) != mesh_bytes(first.mesh)
    assert procedural_asset(kind, 3) is again  # cached


@pytest.mark.parametrize("kind", KINDS)
def test_identity_fields(kind: str) -> None:
    asset = procedural_asset(kind, 2)
    assert isinstance(asset, Asset)
    assert (asset.key, asset.sha256, asset.source) == (f"procedural/{kind}/2", None, f"procedural:{kind}#2")


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("variant", VARIANTS)
def test_conventions(kind: str, variant: int) -> None:
    mesh = procedural_asset(kind, variant).mesh
    v = mesh.vertices
    assert v.dtype == np.float64 and np.all(np.isfinite(v))
    assert v[:, 2].min() == 0.0
    lo, hi = v.min(axis=0), v.max(axis=0)
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2.0, 0.0, atol=1e-9)
    assert 0.04 <= (hi - lo).max() <= 0.45  # metres, typical real sizes
    colours = mesh.visual.vertex_colors
    assert colours.dtype == np.uint8 and colours.shape == (len(v), 4) and np.all(colours[:, 3] == 255)
    assert len(mesh.faces) <= BUDGET[kind]
    assert mesh.area_faces.min() > 1e-12  # no degenerate faces
    assert not v.flags.writeable and not mesh.faces.flags.writeable


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("variant", range(3))
def test_closed_components_wound_outward(kind: str, variant: int) -> None:
    mesh = procedural_asset(kind, variant).mesh
    assert mesh.is_watertight and mesh.is_winding_consistent
    parts = mesh.split(only_watertight=False)
    assert all(p.is_watertight for p in parts)
    assert min(p.volume for p in parts) > 0.0  # positive signed volume: outward normals


def test_urchin_spines_are_many_thin_and_long() -> None:
    for variant in VARIANTS:
        mesh = procedural_asset("urchin", variant).mesh
        parts = sorted(mesh.split(only_watertight=False), key=lambda p: p.volume)
        body, spines = parts[-1], parts[:-1]
        body_radius = np.ptp(body.vertices[:, 0]) / 2.0
        assert 0.025 - 1e-9 <= body_radius <= 0.04 + 1e-9
        assert 60 * 0.8 <= len(spines) <= 200
        for spine in spines[:: max(1, len(spines) // 15)]:
            sides = len(spine.vertices) - 1
            assert 4 <= sides <= 6
            ring, tip = spine.vertices[:-1], spine.vertices[-1]
            base_diameter = 2.0 * np.linalg.norm(ring - ring.mean(axis=0), axis=1).max()
            assert base_diameter <= 0.004  # a few mm at the base
            assert np.linalg.norm(tip - ring.mean(axis=0)) >= 0.3 * body_radius


def test_unknown_kind_and_negative_variant_are_refused() -> None:
    with pytest.raises(ValueError, match=r"'kraken'.*urchin.*pipe"):
        procedural_asset("kraken", 0)
    with pytest.raises(ValueError, match="variant"):
        procedural_asset("rock", -1)


# ------------------------------------------------------------------ user meshes


def coloured_box() -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=[0.1, 0.2, 0.3])
    mesh.apply_translation([1.0, -2.0, 0.5])
    mesh.visual.vertex_colors = np.tile(np.array([10, 20, 30, 255], np.uint8), (len(mesh.vertices), 1))
    return mesh


@pytest.mark.parametrize("ext", ["ply", "obj", "glb", "stl"])
def test_user_mesh_round_trip(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"box.{ext}"
    coloured_box().export(path)
    asset = load_user_asset(path)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert (asset.sha256, asset.key, asset.source) == (digest, f"file/{digest}", f"box.{ext}")
    v = asset.mesh.vertices
    extents = [0.1, 0.3, 0.2] if ext == "glb" else [0.1, 0.2, 0.3]  # glTF +y up becomes +z up
    np.testing.assert_allclose(v.max(axis=0) - v.min(axis=0), extents, atol=1e-6)
    assert v[:, 2].min() == 0.0
    np.testing.assert_allclose((v.min(axis=0) + v.max(axis=0))[:2] / 2.0, 0.0, atol=1e-9)
    assert len(asset.mesh.faces) == 12
    colours = asset.mesh.visual.vertex_colors
    assert colours.dtype == np.uint8
    expected = [128, 128, 128, 255] if ext == "stl" else [10, 20, 30, 255]  # STL carries no colour
    assert np.all(colours == expected)
    assert load_user_asset(path) is asset  # cached by path, mtime and size


def test_user_scene_is_flattened_with_transforms(tmp_path: Path) -> None:
    scene = trimesh.Scene()
    for x in (0.0, 3.0):
        scene.add_geometry(trimesh.creation.box(extents=[1, 1, 1]),
                           transform=trimesh.transformations.translation_matrix([x, 0, 0]))
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh = load_user_asset(path).mesh
    assert len(mesh.faces) == 24
    np.testing.assert_allclose(mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0), [4, 1, 1], atol=1e-6)


def test_changed_file_is_reloaded(tmp_path: Path) -> None:
    path = tmp_path / "m.ply"
    coloured_box().export(path)
    first = load_user_asset(path)
    trimesh.creation.icosphere(subdivisions=1).export(path)
    second = load_user_asset(path)
    assert second.sha256 != first.sha256 and len(second.mesh.faces) == 80


@pytest.mark.parametrize("name, content, reason", [
    ("missing.ply", None, "not found"),
    ("garbage.ply", b"\x00\x01garbage" * 20, "cannot parse"),
    ("garbage.glb", b"\x00\x01garbage" * 20, "cannot parse"),
    ("empty.obj", b"", "no triangles"),
    ("points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),
    ("mesh.xyz", b"0 0 0\n", "unsupported"),
])
def test_bad_user_files_raise_asset_error_naming_them(tmp_path: Path, name: str, content: bytes | None,
                                                      reason: str) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(AssetError, match=reason) as info:
        load_user_asset(path)
    assert name in str(info.value)
    assert isinstance(info.value, ValueError)
