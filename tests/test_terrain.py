"""Tests for procedural seabed terrains, height lookup, image textures and user terrain meshes."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.ndimage import gaussian_filter

from seasynth.worker.scene.assets import AssetError
from seasynth.worker.scene.assets.terrain import (
    STYLES,
    Terrain,
    grid_faces,
    heightfield,
    procedural_terrain,
    with_material,
)
from seasynth.worker.scene.assets.user import load_user_terrain, load_user_texture
from seasynth.worker.scene.materials import material_key, terrain_uv, user_material

SIZE, CELLS, RELIEF = 4.0, 64, 0.3


def terrain_bytes(t: Terrain) -> bytes:
    return t.mesh.vertices.tobytes() + t.mesh.faces.tobytes() + t.mesh.visual.vertex_colors.tobytes()


@pytest.mark.parametrize("style", STYLES)
def test_grid_layout_and_conventions(style: str) -> None:
    t = procedural_terrain(style, 0, SIZE, CELLS, RELIEF)
    assert t.heights.shape == (CELLS + 1, CELLS + 1) and t.heights.dtype == np.float32
    assert t.extent == (-SIZE / 2, SIZE / 2, -SIZE / 2, SIZE / 2)
    v = t.mesh.vertices
    axis = np.linspace(-SIZE / 2, SIZE / 2, CELLS + 1)
    gx, gy = np.meshgrid(axis, axis)
    np.testing.assert_array_equal(v[:, :2], np.column_stack([gx.ravel(), gy.ravel()]))
    np.testing.assert_array_equal(v[:, 2], t.heights.ravel())
    assert t.heights.min() == 0.0
    assert RELIEF <= np.ptp(t.heights) <= RELIEF + 0.08  # large-scale relief plus a few cm of detail
    assert len(t.mesh.faces) == 2 * CELLS * CELLS
    assert np.all(t.mesh.face_normals[:, 2] > 0)  # wound to face +z
    colours = t.mesh.visual.vertex_colors
    assert colours.dtype == np.uint8 and colours.shape == (len(v), 4)
    assert colours[:, :3].astype(float).std(axis=0).min() > 2.0  # varies with position
    assert not v.flags.writeable and not t.heights.flags.writeable


def test_grid_faces_point_up_on_a_flat_grid() -> None:
    xs, ys = np.meshgrid(np.arange(4.0), np.arange(3.0))
    mesh = trimesh.Trimesh(np.column_stack([xs.ravel(), ys.ravel(), np.zeros(12)]), grid_faces(4, 3), process=False)
    np.testing.assert_array_equal(mesh.face_normals, np.tile([0.0, 0.0, 1.0], (12, 1)))
    assert mesh.area == pytest.approx(6.0)


@pytest.mark.parametrize("style", STYLES)
def test_determinism_cache_and_keys(style: str) -> None:
    first = procedural_terrain(style, 1, SIZE, CELLS, RELIEF)
    procedural_terrain.cache_clear()
    again = procedural_terrain(style, 1, SIZE, CELLS, RELIEF)
    assert again is not first and terrain_bytes(again) == terrain_bytes(first) and again == first
    assert procedural_terrain(style, 1, SIZE, CELLS, RELIEF) is again
    other = procedural_terrain(style, 2, SIZE, CELLS, RELIEF)
    assert terrain_bytes(other) != terrain_bytes(first)
    keys = {first.key, other.key, procedural_terrain(style, 1, SIZE * 2, CELLS, RELIEF).key,
            procedural_terrain(style, 1, SIZE, CELLS // 2, RELIEF).key,
            procedural_terrain(style, 1, SIZE, CELLS, RELIEF * 2).key}
    assert len(keys) == 5 and all(style in k for k in keys)


def test_heightfield_key_names_content() -> None:
    a = heightfield(np.random.default_rng(0), "sand", SIZE, 16, RELIEF)
    b = heightfield(np.random.default_rng(1), "sand", SIZE, 16, RELIEF)
    c = heightfield(np.random.default_rng(0), "sand", SIZE, 16, RELIEF)
    assert a.key != b.key and a.key == c.key


def test_height_at_matches_vertices_and_is_bilinear() -> None:
    t = procedural_terrain("rock", 0, SIZE, CELLS, RELIEF)
    v = t.mesh.vertices
    np.testing.assert_allclose(t.height_at(v[:, :2]), v[:, 2], rtol=0, atol=1e-12)
    rng = np.random.default_rng(5)
    ix, iy = rng.integers(0, CELLS, 200), rng.integers(0, CELLS, 200)
    tx, ty = rng.random(200), rng.random(200)
    step = SIZE / CELLS
    xy = np.column_stack([-SIZE / 2 + (ix + tx) * step, -SIZE / 2 + (iy + ty) * step])
    h = t.heights.astype(np.float64)
    expected = ((h[iy, ix] * (1 - tx) + h[iy, ix + 1] * tx) * (1 - ty)
                + (h[iy + 1, ix] * (1 - tx) + h[iy + 1, ix + 1] * tx) * ty)
    np.testing.assert_allclose(t.height_at(xy), expected, rtol=0, atol=1e-9)
    # Outside the extent: clamped to the nearest edge; shape follows the input's leading axes.
    np.testing.assert_allclose(t.height_at(np.array([[-10.0, -10.0], [10.0, 10.0]])), [h[0, 0], h[-1, -1]])
    assert t.height_at(np.zeros((3, 4, 2))).shape == (3, 4)


@settings(max_examples=60, deadline=None)
@given(style=st.sampled_from(STYLES), size=st.one_of(st.sampled_from([5e-324, 1e-323, 1e-310, 1e-300, 1000.0]),
                                                     st.floats(5e-324, 1000.0)),
       cells=st.integers(1, 12), relief=st.floats(0.0, 100.0), seed=st.integers(0, 2**32 - 1),
       xy=st.lists(st.floats(-1e6, 1e6), min_size=2, max_size=2))
def test_a_heightfield_of_any_size_is_finite_and_height_at_stays_within_it(style, size, cells, relief, seed, xy):
    """terrain.size_m may be any float > 0 (a subnormal one halves to an extent of no width)."""
    t = heightfield(np.random.default_rng(seed), style, size, cells, relief)
    h = t.heights.astype(np.float64)
    assert np.all(np.isfinite(h)) and h.min() == 0.0 and np.all(np.isfinite(t.mesh.vertices))
    points = np.array([xy, [0.0, 0.0], [t.extent[0], t.extent[2]], [t.extent[1], t.extent[3]]])
    at = t.height_at(points)
    assert np.all(np.isfinite(at)) and np.all((at >= h.min()) & (at <= h.max()))


def roughness(h: np.ndarray) -> float:
    """RMS height (m) left after removing features wider than a few cells."""
    h = h.astype(np.float64)
    return float(np.sqrt(np.mean((h - gaussian_filter(h, 2.0)) ** 2)))


def test_styles_differ_pebbles_roughest_sand_smoothest() -> None:
    for variant in range(3):
        r = {s: roughness(procedural_terrain(s, variant, SIZE, CELLS, RELIEF).heights) for s in STYLES}
        assert r["pebbles"] > 1.2 * r["rock"] > 1.2 * 1.2 * r["sand"], r
        spread = {s: procedural_terrain(s, variant, SIZE, CELLS, RELIEF).mesh.visual.vertex_colors[:, :3]
                  .astype(float).std(axis=0).mean() for s in STYLES}
        assert spread["pebbles"] > 2.0 * max(spread["sand"], spread["rock"]), spread  # one colour per pebble
        mean = {s: procedural_terrain(s, variant, SIZE, CELLS, RELIEF).mesh.visual.vertex_colors[:, :3]
                .astype(float).mean() for s in STYLES}
        assert mean["sand"] > mean["pebbles"] > mean["rock"], mean  # pale sand, dark rock


def test_zero_relief_sand_is_ripples_only() -> None:
    t = procedural_terrain("sand", 0, SIZE, CELLS, 0.0)
    assert 0.004 <= np.ptp(t.heights) <= 0.016


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match=r"'lava'.*sand"):
        procedural_terrain("lava", 0, SIZE, CELLS, RELIEF)
    with pytest.raises(ValueError, match="cells"):
        procedural_terrain("sand", 0, SIZE, 0, RELIEF)
    with pytest.raises(ValueError, match="variant"):
        procedural_terrain("sand", -1, SIZE, CELLS, RELIEF)


# ------------------------------------------------------------------ textures


def test_a_user_texture_set_is_drawn_per_pixel_on_a_white_terrain(tmp_path: Path) -> None:
    image = np.zeros((2, 2, 3), np.uint8)
    image[0, 0], image[0, 1], image[1, 0], image[1, 1] = [255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]
    path = tmp_path / "quad.png"
    Image.fromarray(image).save(path)
    t = procedural_terrain("sand", 0, 2.0, 8, RELIEF)
    texture = load_user_texture(path)
    assert texture.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    np.testing.assert_array_equal(texture.pixels, image)
    assert load_user_texture(path) is texture  # cached by path, mtime and size
    material = user_material(texture, None, None, 0.01, 1.0)
    assert material.base.pixels is texture.pixels and material.base.srgb and material.normal is None
    textured = with_material(t, material, material_key(material), True, 1.0)
    v = textured.mesh.vertices
    np.testing.assert_array_equal(v, t.mesh.vertices)
    assert (textured.mesh.visual.vertex_colors == 255).all()  # the image is the colour
    assert textured.material is material and textured.tile_m == 1.0
    assert textured.key != t.key and t.key in textured.key
    assert with_material(t, material, material_key(material), True, 1.0) is textured
    np.testing.assert_array_equal(textured.height_at(v[:, :2]), t.height_at(v[:, :2]))
    # The image's top-left corner sits at (0, tile_m) and its rows run towards -y: texture coordinates u = x / tile,
    # v = -y / tile, so the top-left texel's centre (0.25, 0.25) is at x = 0.25, y = 0.75 (mod 1).
    np.testing.assert_allclose(terrain_uv(np.array([[0.25, 0.75, 0.0]]), 1.0, warp=False) % 1.0, [[0.25, 0.25]])


def test_a_height_map_becomes_the_normal_map_of_its_relief(tmp_path: Path) -> None:
    ramp = np.tile(np.linspace(0, 255, 16).astype(np.uint8)[None, :, None], (16, 1, 3))  # rising to the right
    path = tmp_path / "height.png"
    Image.fromarray(ramp).save(path)
    albedo = tmp_path / "albedo.png"
    Image.fromarray(np.full((4, 4, 3), 128, np.uint8)).save(albedo)
    material = user_material(load_user_texture(albedo), None, load_user_texture(path), 0.05, 1.0)
    n = material.normal.pixels.astype(float) / 255.0 * 2.0 - 1.0
    inner = n[:, 2:-2]  # away from the periodic wrap, where the ramp falls back
    assert (inner[..., 0] < -0.01).all() and np.abs(inner[..., 1]).max() < 0.01  # tilted away from the rise
    assert material.mapping == "uv"


def test_load_user_texture_bad_image(tmp_path: Path) -> None:
    bad = tmp_path / "noise.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(AssetError, match=r"noise\.png: cannot decode image"):
        load_user_texture(bad)
    with pytest.raises(AssetError, match=r"nothing\.png: file not found"):
        load_user_texture(tmp_path / "nothing.png")


# ------------------------------------------------------------------ user terrain


def test_user_terrain_height_at_is_exact_on_a_tilted_plane(tmp_path: Path) -> None:
    n = 21
    xs, ys = np.meshgrid(np.linspace(0.0, 4.0, n), np.linspace(10.0, 13.0, n))
    z = 0.1 * xs - 0.05 * ys + 2.0
    mesh = trimesh.Trimesh(np.column_stack([xs.ravel(), ys.ravel(), z.ravel()]), grid_faces(n, n), process=False)
    path = tmp_path / "seabed.ply"
    mesh.export(path)
    t = load_user_terrain(path)
    assert t.heights is None and t.key.startswith("terrain/file/")
    assert t.extent == pytest.approx((-2.0, 2.0, -1.5, 1.5))
    assert t.mesh.vertices[:, 2].min() == 0.0
    rng = np.random.default_rng(0)
    xy = rng.uniform([-2.0, -1.5], [2.0, 1.5], (500, 2))
    # Centred on x, y and lifted so the lowest corner (x, y) = (-2, 1.5) is at z = 0.
    expected = 0.1 * (xy[:, 0] + 2.0) - 0.05 * (xy[:, 1] - 1.5)
    np.testing.assert_allclose(t.height_at(xy), expected, rtol=0, atol=1e-6)  # PLY stores float32
    assert load_user_terrain(path) is t


def test_user_terrain_bad_file(tmp_path: Path) -> None:
    path = tmp_path / "seabed.stl"
    path.write_bytes(b"")
    with pytest.raises(AssetError, match="seabed.stl"):
        load_user_terrain(path)


# ------------------------------------------------------------------ textures in frames


def test_texture_is_read_once_per_process_and_frames_are_unchanged(tmp_path: Path, monkeypatch,
                                                                   render_session) -> None:
    import subprocess
    import sys

    from seasynth.service.spec.dataset import load_spec

    image = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    texture = tmp_path / "seabed.png"
    Image.fromarray(image).save(texture)
    example = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
    overrides = {"frames": 2, "camera.width": 48, "camera.height": 36, "terrain.texture.path": str(texture)}
    spec = load_spec(example, overrides)

    reads: list[Path] = []
    read_bytes = Path.read_bytes

    def counting(self: Path) -> bytes:
        if self.resolve() == texture.resolve():
            reads.append(self)
        return read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", counting)
    first = render_session.frame_files(spec, 0)
    second = render_session.frame_files(spec, 1)
    assert len(reads) == 1  # the first frame read it; the second used the decoded image
    monkeypatch.undo()
    # The same frame from a fresh process (which reads and decodes the file itself) is byte-identical.
    spec_file, out = tmp_path / "spec.json", tmp_path / "fresh"
    spec_file.write_text(spec.model_dump_json())
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "reproduce", str(spec_file), "--frame", "1", "--out",
                        str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert {rel: (out / rel).read_bytes() for rel in second} == second
    assert first != second


def test_a_non_square_height_map_slopes_as_its_image_spans_the_tile_both_ways(tmp_path: Path) -> None:
    """The image spans texture_tile_m along its width and along its height, so columns and rows are tile / w and
    tile / h apart: one sine cycle across the tile slopes alike along either axis."""
    h, w = 32, 64
    along_x = (127.5 + 127.5 * np.sin(2 * np.pi * np.arange(w) / w))[None, :].repeat(h, 0)
    along_y = (127.5 + 127.5 * np.sin(2 * np.pi * np.arange(h) / h))[:, None].repeat(w, 1)
    albedo = tmp_path / "albedo.png"
    Image.fromarray(np.full((4, 4, 3), 128, np.uint8)).save(albedo)
    slopes = []
    for name, grey in (("x.png", along_x), ("y.png", along_y)):
        Image.fromarray(np.round(grey).astype(np.uint8)).convert("RGB").save(tmp_path / name)
        m = user_material(load_user_texture(albedo), None, load_user_texture(tmp_path / name), 0.05, 1.0)
        n = m.normal.pixels.astype(float) / 255.0 * 2.0 - 1.0
        slopes.append(np.abs(n[..., :2]).max())
    # 0.05 m over one cycle of 1 m: slope 0.157 at most, a tangent's normal tilts by about that much
    assert slopes[0] == pytest.approx(slopes[1], abs=0.02) and 0.12 < slopes[0] < 0.2
