"""An uploaded mesh's picture drawn without OpenGL (seasynth.api.mesh_thumbnail), and drawn in the upload's check
(seasynth.api.mesh_check): z-buffering that keeps each pixel's nearest triangle, a convex mesh's silhouette exactly
its projected hull, the mesh fitted to the margins, glTF turned +z up as workers turn it, and a picture that fails
leaving the mesh valid."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial import ConvexHull

from seasynth.api import mesh_check, mesh_thumbnail
from seasynth.api.mesh_thumbnail import draw, project, rasterise, view_axes

seeds = st.integers(0, 2**32 - 1)
views = st.tuples(st.floats(-180, 180), st.floats(-80, 80))


def brute_force(tri: np.ndarray, width: int, height: int) -> np.ndarray:
    """(m, h, w): each triangle's depth at each pixel centre it covers (-inf elsewhere), all at once."""
    cx, cy = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    a, b, c = (tri[:, k, :, None, None] for k in range(3))
    den = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    ok = np.abs(den) >= 1e-12
    den = np.where(ok, den, 1.0)
    wb = ((cx - a[:, 0]) * (c[:, 1] - a[:, 1]) - (cy - a[:, 1]) * (c[:, 0] - a[:, 0])) / den
    wc = ((b[:, 0] - a[:, 0]) * (cy - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cx - a[:, 0])) / den
    wa = 1 - wb - wc
    inside = ok & (wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9)
    return np.where(inside, wa * a[:, 2] + wb * b[:, 2] + wc * c[:, 2], -np.inf)


@settings(max_examples=60, deadline=None)
@given(seed=seeds, m=st.integers(1, 12), chunk=st.integers(1, 400))
def test_each_pixel_keeps_its_nearest_triangle_in_chunks_of_any_size(seed, m, chunk):
    rng = np.random.default_rng(seed)
    w, h = 24, 18
    tri = np.concatenate([rng.uniform(-4, 28, (m, 3, 1)), rng.uniform(-4, 22, (m, 3, 1)),
                          rng.uniform(-5, 5, (m, 3, 1))], axis=2)
    depths = brute_force(tri, w, h)
    face, depth = rasterise(tri, w, h)
    np.testing.assert_allclose(depth, depths.max(axis=0), rtol=0, atol=1e-9)
    want_face = np.where(np.isfinite(depths).any(axis=0), depths.argmax(axis=0), -1)
    top = np.sort(np.concatenate([depths, np.full((1, h, w), -np.inf)]), axis=0)
    with np.errstate(invalid="ignore"):  # -inf - -inf: a pixel no triangle covers (nan, so untied)
        untied = ~(top[-1] - top[-2] <= 1e-9)
    assert (face[untied] == want_face[untied]).all()
    old = mesh_thumbnail.CHUNK_SAMPLES
    mesh_thumbnail.CHUNK_SAMPLES = chunk
    try:
        again = rasterise(tri, w, h)
    finally:
        mesh_thumbnail.CHUNK_SAMPLES = old
    assert (again[0] == face).all() and (again[1] == depth).all()


@settings(max_examples=40, deadline=None)
@given(seed=seeds, view=views, n=st.integers(4, 40))
def test_a_convex_meshs_silhouette_is_its_projected_hull(seed, view, n):
    rng = np.random.default_rng(seed)
    hull = trimesh.convex.convex_hull(rng.normal(size=(n, 3)) * rng.uniform(0.1, 5, 3))
    w, h = 64, 48
    screen = project(hull.vertices, view_axes(*view), w, h)
    face, _ = rasterise(screen[hull.faces], w, h)
    outline = ConvexHull(screen[:, :2])
    cx, cy = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    # signed distance to each edge line (normalised): inside where every one is <= 0
    dist = (outline.equations[:, :2] @ np.stack([cx.ravel(), cy.ravel()]) + outline.equations[:, 2:]).max(axis=0)
    sure = np.abs(dist) > 1e-6
    assert ((face.ravel() >= 0) == (dist <= 0))[sure].all()


@settings(max_examples=60, deadline=None)
@given(seed=seeds, view=views, scale=st.floats(1e-3, 1e3))
def test_the_mesh_is_fitted_centred_to_the_margins_on_its_limiting_side(seed, view, scale):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(20, 3)) * rng.uniform(0.05, 5, 3) * scale + rng.normal(size=3) * scale
    w, h, m = 128, 96, mesh_thumbnail.MARGIN
    screen = project(points, view_axes(*view), w, h)
    lo, hi = screen[:, :2].min(axis=0), screen[:, :2].max(axis=0)
    np.testing.assert_allclose((lo + hi) / 2, [w / 2, h / 2], atol=1e-9)
    room = (1 - 2 * m) * np.array([w, h])
    assert ((hi - lo) <= room + 1e-9).all() and np.isclose(((hi - lo) / room).max(), 1)


@settings(max_examples=40, deadline=None)
@given(extents=st.tuples(*[st.floats(0.01, 20)] * 3))
def test_the_picture_is_the_flat_shaded_mesh_within_its_projection(extents):
    box = trimesh.creation.box(extents=extents)
    rgba = draw(box.vertices, box.faces)
    assert rgba.shape == (96, 128, 4) and rgba.dtype == np.uint8
    screen = project(box.vertices, view_axes(mesh_thumbnail.AZIMUTH_DEG, mesh_thumbnail.ELEVATION_DEG), 128, 96)
    rows, cols = np.nonzero(rgba[..., 3])
    assert len(rows) > 0  # however thin (a needle of 0.01 by 20 fits in 0.04 of a pixel's width), a box shows
    # nothing drawn outside the pixels the projection's bounding box touches
    lo, hi = screen[:, :2].min(axis=0), screen[:, :2].max(axis=0)
    assert cols.min() >= np.floor(lo[0]) and cols.max() <= np.ceil(hi[0]) - 1
    assert rows.min() >= np.floor(lo[1]) and rows.max() <= np.ceil(hi[1]) - 1
    # a fully covered pixel is the clay colour at a shade between the ambient light and full light
    shade = rgba[rgba[..., 3] == 255, :3] / mesh_thumbnail.COLOUR
    assert (shade >= mesh_thumbnail.AMBIENT - 0.01).all() and (shade <= 1 + 0.01).all()


@settings(max_examples=30, deadline=None)
@given(thin=st.floats(1e-4, 0.05), long=st.floats(5.0, 50.0), axis=st.integers(0, 2), turn=st.floats(0.0, 360.0))
def test_a_needle_or_a_sheet_seen_edge_on_shows_along_its_whole_length(thin, long, axis, turn):
    """Thinner than the samples' spacing, such a mesh would fall between pixel centres: its triangles are drawn
    along their edges, a point every sample step: every point of the needle's axis is within a pixel of a drawn one
    (a step can pass a pixel's corner by), and nothing is drawn beyond its projection's pixels."""
    extents = [thin, thin, thin]
    extents[axis] = long
    needle = trimesh.creation.box(extents=extents)
    first = needle.vertices[:, axis] < 0  # the corners at one end (turning keeps the vertices' order)
    needle.apply_transform(trimesh.transformations.rotation_matrix(np.radians(turn), [0, 0, 1]))
    rgba = draw(needle.vertices, needle.faces)
    screen = project(needle.vertices, view_axes(mesh_thumbnail.AZIMUTH_DEG, mesh_thumbnail.ELEVATION_DEG), 128, 96)
    ends = [screen[first, :2].mean(axis=0), screen[~first, :2].mean(axis=0)]
    for f in np.linspace(0.02, 0.98, 200):  # points along the axis, off its ends' pixels
        col, row = np.floor(ends[0] + f * (ends[1] - ends[0])).astype(int)
        assert rgba[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2, 3].any(), (f, col, row)
    lo, hi = screen[:, :2].min(axis=0), screen[:, :2].max(axis=0)
    rows, cols = np.nonzero(rgba[..., 3])
    assert cols.min() >= np.floor(lo[0]) - 1 and cols.max() <= np.ceil(hi[0]) and rows.min() >= np.floor(lo[1]) - 1
    assert rows.max() <= np.ceil(hi[1])
    sheet = trimesh.creation.box(extents=[long, long, thin])  # seen from 30 degrees above: not edge-on, drawn whole
    assert (draw(sheet.vertices, sheet.faces)[..., 3] > 0).sum() > 100


def check_with_picture(tmp_path: Path, name: str, data: bytes) -> tuple[dict, bytes | None]:
    src, out = tmp_path / name, tmp_path / (name + ".thumb.png")
    src.write_bytes(data)
    answer = mesh_check.check(str(src), name.rsplit(".", 1)[1], name, tmp_path, out)
    return answer, out.read_bytes() if out.exists() else None


def test_the_check_draws_a_valid_meshs_picture_with_gltf_turned_z_up(tmp_path):
    tall_y = trimesh.creation.box(extents=(0.2, 1.0, 0.3))
    tall_z = trimesh.creation.box(extents=(0.2, 0.3, 1.0))
    answer, glb = check_with_picture(tmp_path, "tall.glb", tall_y.export(file_type="glb"))
    assert answer == {"ok": True}
    answer, ply = check_with_picture(tmp_path, "tall.ply", tall_z.export(file_type="ply"))
    assert answer == {"ok": True} and ply == mesh_thumbnail.png(tall_z.vertices, tall_z.faces)
    a, b = (np.asarray(Image.open(io.BytesIO(p)), dtype=np.int16) for p in (glb, ply))
    assert (a[..., 3] > 0).sum() == (b[..., 3] > 0).sum() and np.abs(a - b).max() <= 2


def test_a_picture_that_fails_leaves_the_mesh_valid_and_says_why(tmp_path, monkeypatch):
    def fail(vertices, faces):
        raise MemoryError("drawing")

    monkeypatch.setattr(mesh_thumbnail, "png", fail)
    answer, picture = check_with_picture(tmp_path, "box.stl", trimesh.creation.box().export(file_type="stl"))
    assert answer == {"ok": True, "thumbnail_error": "MemoryError: drawing"} and picture is None
    answer, picture = check_with_picture(tmp_path, "bad.obj", b"v 0 0 0\n")  # not a mesh: no picture asked for
    assert answer == {"error": "bad.obj: the obj mesh has no triangles"} and picture is None


@pytest.mark.parametrize("count", [0, 1])
def test_degenerate_meshes_draw_nothing_without_failing(count):
    v = np.zeros((3, 3)) if count == 0 else np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    rgba = draw(v, np.array([[0, 1, 2]]))
    assert rgba.shape == (96, 128, 4) and not rgba[..., 3].any()
