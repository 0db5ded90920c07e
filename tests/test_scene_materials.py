"""The scene's materials (worker.scene.materials, worker.scene.texture_cache): the terrain's warped texture
coordinates stretch a texture by under 15% anywhere and agree wherever they are asked; procedural families map as
documented; texture sets read through a shared folder are the built ones."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.scene.assets.procedural import procedural_asset
from seasynth.worker.scene.assets.textures import texture_set
from seasynth.worker.scene.disk_cache import share_in
from seasynth.worker.scene.materials import (
    WARP_FREQUENCY,
    asset_material,
    style_material,
    terrain_uv,
    uv_warp,
)
from seasynth.worker.scene.texture_cache import _load, shared_texture_set

coords = st.floats(-500.0, 500.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(x=coords, y=coords, angle=st.floats(0.0, 2 * np.pi), tile=st.floats(0.05, 5.0))
def test_the_warp_stretches_a_texture_by_under_15_percent(x, y, angle, tile):
    """The Jacobian of the warped coordinates against the unwarped ones stays within 15% of the identity: a
    repeated texture moves (its repeats no longer line up) without visibly stretching."""
    h = 1e-4
    p = np.array([[x, y, 0.0]])
    d = np.array([[np.cos(angle), np.sin(angle), 0.0]]) * h * tile
    du = (terrain_uv(p + d, tile).astype(np.float64) - terrain_uv(p - d, tile)) / (2 * h)
    plain = (terrain_uv(p + d, tile, warp=False).astype(np.float64) - terrain_uv(p - d, tile, warp=False)) / (2 * h)
    # float32 coordinates of up to 1e4 repeats resolve about 1e-3 repeats: the difference quotient over 2e-4 repeats
    # is then too coarse, so the stretch is taken on the float64 warp directly
    q = p[:, :2] / tile * [1.0, -1.0]
    e = d[:, :2] / (h * tile) * [1.0, -1.0]
    jac = (uv_warp(q + h * e) - uv_warp(q - h * e)) / (2 * h)
    assert np.linalg.norm(jac) <= 0.15 * np.linalg.norm(e)
    assert np.isfinite(du).all() and np.isfinite(plain).all()


@settings(max_examples=30, deadline=None)
@given(xy=st.lists(st.tuples(coords, coords), min_size=1, max_size=20), split=st.integers(0, 20))
def test_the_warp_is_a_function_of_the_position_alone(xy, split):
    """Tile and far-field rings ask for their own vertices: a point gets the same coordinates in any batch."""
    p = np.array(xy, np.float64)
    whole = uv_warp(p)
    parts = np.concatenate([uv_warp(p[:split]), uv_warp(p[split:])]) if 0 < split < len(p) else uv_warp(p)
    np.testing.assert_array_equal(whole, parts)
    assert np.abs(whole).max() <= 0.3 + 1e-12


def test_the_warp_moves_repeats_off_the_grid():
    """Across 40 repeats the displacement varies by more than a third of a repeat: the repeats do not line up."""
    q = np.stack(np.meshgrid(np.arange(40.0), np.arange(40.0)), -1).reshape(-1, 2)
    w = uv_warp(q)
    assert np.ptp(w[:, 0]) > 1 / 3 and np.ptp(w[:, 1]) > 1 / 3
    assert WARP_FREQUENCY * 40 >= 4  # several features over the span checked


def test_procedural_families_map_as_documented():
    spec = DatasetSpec()
    urchin = asset_material(procedural_asset("urchin", 3), 3, spec)
    assert urchin.mapping == "triplanar" and urchin.base.source == "procedural:urchin#3"
    assert urchin.triplanar_per_m == 1.0 / texture_set("urchin", 3, 64).tile_m
    rock = asset_material(procedural_asset("rock", 5), 5, spec)
    assert rock.base.source == f"procedural:stone#{5 % spec.materials.variants}"
    sand = style_material("sand", 6, spec)
    assert sand.mapping == "uv" and sand.base.source == f"procedural:sand#{6 % spec.materials.variants}"
    assert sand.anisotropy == spec.materials.anisotropy and sand.base.srgb and not sand.normal.srgb
    off = DatasetSpec.model_validate({"materials": {"procedural": False}})
    assert asset_material(procedural_asset("urchin", 3), 3, off) is None and style_material("sand", 6, off) is None


def test_a_texture_set_read_from_the_shared_folder_is_the_built_one(tmp_path):
    try:
        share_in(tmp_path)
        shared_texture_set.cache_clear()
        first = shared_texture_set("coral", 2, 64)  # built and stored
        stored = list(tmp_path.glob("texture-*.npz"))
        assert len(stored) == 1
        read = _load(stored[0])
        built = texture_set("coral", 2, 64)
        for got in (first, read):
            assert got.key == built.key and got.albedo_gain == built.albedo_gain and got.tile_m == built.tile_m
            np.testing.assert_array_equal(got.albedo, built.albedo)
            np.testing.assert_array_equal(got.normal, built.normal)
            assert not got.albedo.flags.writeable
        stored[0].write_bytes(b"damaged")
        assert _load(stored[0]) is None  # built again by whoever meets it
    finally:
        share_in(None)
        shared_texture_set.cache_clear()


def test_a_user_mesh_s_textures_are_filtered_as_the_spec_says():
    from pathlib import Path

    from seasynth.worker.scene.assets.user import load_user_asset
    from seasynth.worker.scene.materials import user_surface

    asset = load_user_asset(Path(__file__).resolve().parents[1] / "examples" / "assets" / "marker.glb")
    assert asset.surface is not None
    for anisotropy in (1, 4, 16):
        spec = DatasetSpec.model_validate({"materials": {"anisotropy": anisotropy}})
        got = user_surface(asset, spec)
        assert user_surface(asset, spec) is got  # cached by asset and setting
        assert [m.anisotropy for _, _, m in got.groups if m is not None] == [float(anisotropy)] * sum(
            m is not None for _, _, m in asset.surface.groups)
        assert got.uv is asset.surface.uv and [g[:2] for g in got.groups] == [g[:2] for g in asset.surface.groups]
