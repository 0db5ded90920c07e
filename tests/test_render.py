"""Tests of the GL renderer's geometry: range at pixel centres, z-depth against range, open water, determinism."""

import io

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import DEPTH_SCALE, PRESETS, depth_png16, ray_norms, to_render_mesh
from seasynth.worker.render import DrawItem, Lighting, Passes, Sampling, View, WaterParams, normal_matrix
from seasynth.worker.scene.poses import rotation_between

EXAMPLE = "examples/urchins.yaml"
LIGHT = Lighting(sun_dir_world=np.array([0.0, -1.0, 0.0]), sun_intensity=1.0, ambient=0.2)


def pinhole(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) K with square pixels and the principal point at the image centre (pixel centres at integers)."""
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def camera_view(K: np.ndarray, width: int, height: int, near: float = 0.1, far: float = 1e4) -> View:
    """A view whose world frame is the camera frame (KITTI axes: x right, y down, z forward)."""
    return View(K=K, width=width, height=height, cam_from_world=np.eye(4), near=near, far=far)


def draw(key: str, mesh: trimesh.Trimesh, instance_id: int = 1, pose: np.ndarray | None = None) -> DrawItem:
    return DrawItem(
        mesh=to_render_mesh(key, mesh),
        world_from_obj=np.eye(4) if pose is None else pose,
        albedo_scale=np.ones(3, np.float32),
        albedo_bias=np.zeros(3, np.float32),
        instance_id=instance_id,
    )


def slab(normal: np.ndarray, point: np.ndarray, size_m: float = 4000.0) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A 1 m thick square slab whose camera-facing side is the plane through `point` with unit `normal`
    (pointing away from the camera), and its pose."""
    mesh = trimesh.creation.box(extents=[size_m, size_m, 1.0])
    pose = np.eye(4)
    pose[:3, :3] = rotation_between(np.array([0.0, 0.0, 1.0]), normal)
    pose[:3, 3] = point + 0.5 * normal
    return mesh, pose


def pixel_aligned_plane(
    K: np.ndarray, width: int, height: int, normal: np.ndarray, point: np.ndarray, rgb=(200, 120, 60), margin=0.5
) -> trimesh.Trimesh:
    """The plane through `point` with unit `normal` (camera frame) as a quad whose corners project exactly onto the
    image's corners widened by `margin` pixels; the image must see only its front side.

    Rasterisers snap vertices to a sub-pixel grid (NVIDIA: 1/256 pixel) and interpolate from the snapped positions,
    which moves a receding plane's per-pixel range by the snap times its gradient: 1e-3 relative on a 9x7 view of a
    slab whose corners lie anywhere. Corners already on that grid (margin a multiple of 1/256) are not moved, so
    the range is as exact as float32 makes it.
    """
    u = np.array([-margin, width - 1 + margin, width - 1 + margin, -margin])
    v = np.array([-margin, -margin, height - 1 + margin, height - 1 + margin])
    d = np.stack([u, v, np.ones(4)], axis=-1) @ np.linalg.inv(K).T
    t = (normal @ point) / (d @ normal)
    assert np.all(t > 0), "a corner's ray misses the plane's front"
    colours = np.tile(np.array([*rgb, 255], np.uint8), (4, 1))
    return trimesh.Trimesh(d * t[:, None], [[0, 1, 2], [0, 2, 3]], vertex_colors=colours, process=False)


def rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h, w, 3) float64: K^-1 [u, v, 1] at every pixel centre."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T


def corners_and_centre(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the four corner pixels and the centre pixel (odd sizes)."""
    rows = np.array([0, 0, height - 1, height - 1, height // 2])
    cols = np.array([0, width - 1, 0, width - 1, width // 2])
    return rows, cols


# --- range ----------------------------------------------------------------------------------------------------

W, H = 9, 7  # odd, so there is a centre pixel
K_WIDE = pinhole(W, H, 120.0)


@pytest.mark.parametrize(
    "normal",
    [np.array([0.0, 0.0, 1.0]), np.array([0.35, -0.25, 1.0]) / np.linalg.norm([0.35, -0.25, 1.0])],
    ids=["fronto-parallel", "oblique"],
)
def test_range_matches_the_ray_plane_intersection_across_a_120_degree_view(renderer, normal):
    point = np.array([0.0, 0.0, 100.0])
    mesh = pixel_aligned_plane(K_WIDE, W, H, normal, point)
    result = renderer.render(
        camera_view(K_WIDE, W, H), [draw(f"test/render/plane/{normal.tobytes().hex()}", mesh)],
        LIGHT, None, PRESETS["default"], Passes(range=True),
    )
    d = rays(K_WIDE, W, H)
    expected = (normal @ point) / (d @ normal) * np.linalg.norm(d, axis=-1)
    assert result.range_m.dtype == np.float32 and result.range_m.shape == (H, W)
    assert result.instance is None and result.clean is None
    rows, cols = corners_and_centre(W, H)
    np.testing.assert_allclose(result.range_m[rows, cols], expected[rows, cols], rtol=1e-3)
    np.testing.assert_allclose(result.range_m, expected, rtol=1e-3)
    # The view really is wide: at the corners the ray is about twice as long as at the centre.
    assert expected[0, 0] > 1.8 * expected[H // 2, W // 2]


@pytest.mark.parametrize("preset", ["draft", "default"])
def test_range_matches_a_trimesh_ray_cast_across_a_120_degree_view_at_100_m(renderer, preset):
    """From inside a coarse sphere of radius 100 m every pixel centre's ray hits a facet: the renderer's range
    equals trimesh's ray cast of the same facets through each pixel centre, the corners of the view included."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=100.0)
    sphere.visual.vertex_colors = np.tile([90, 160, 120, 255], (len(sphere.vertices), 1))
    result = renderer.render(
        camera_view(K_WIDE, W, H), [draw("test/render/inside-sphere", sphere)],
        LIGHT, None, PRESETS[preset], Passes(range=True),
    )
    d = rays(K_WIDE, W, H).reshape(-1, 3)  # camera frame = world frame
    where, ray_index, _ = sphere.ray.intersects_location(np.zeros_like(d), d, multiple_hits=False)
    cast = np.full(len(d), np.nan)
    cast[ray_index] = np.linalg.norm(where, axis=1)
    cast = cast.reshape(H, W)
    assert np.all(np.isfinite(cast))
    np.testing.assert_allclose(result.range_m, cast, rtol=1e-3)
    rows, cols = corners_and_centre(W, H)
    np.testing.assert_allclose(result.range_m[rows, cols], cast[rows, cols], rtol=1e-3)
    # The facets are visible at this tolerance: a smooth sphere (range 100 everywhere) would fail.
    assert cast.min() < 100.0 * (1 - 5e-3)


def test_z_depth_and_range_are_not_confused(renderer):
    z = 100.0
    mesh, pose = slab(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, z]))
    result = renderer.render(
        camera_view(K_WIDE, W, H), [draw("test/render/slab/z-depth", mesh, 1, pose)],
        LIGHT, None, PRESETS["draft"], Passes(ids=True, range=True),
    )
    depth_m = depth_png16(result.range_m, ray_norms(K_WIDE, W, H)) / DEPTH_SCALE
    rows, cols = corners_and_centre(W, H)
    # A fronto-parallel plane has one z-depth everywhere; KITTI depth stores it to 1/256 m.
    assert np.abs(depth_m - z).max() <= 1 / DEPTH_SCALE
    # Range is z-depth times the length of K^-1 [u, v, 1], computed here independently in float64.
    norm = np.linalg.norm(rays(K_WIDE, W, H), axis=-1)
    np.testing.assert_allclose(result.range_m[rows, cols], z * norm[rows, cols], rtol=1e-3)
    assert np.all(result.range_m[rows[:4], cols[:4]] > 1.9 * z)
    np.testing.assert_allclose(ray_norms(K_WIDE, W, H), norm, rtol=1e-6)
    assert np.all(result.instance == 1)


def test_depth_is_rounded_z_and_zero_where_no_surface_or_beyond_256_m():
    K = pinhole(4, 2, 90.0)
    norms = ray_norms(K, 4, 2)
    z = np.array([[np.inf, 10.0, 255.99, 256.0], [0.0, 1e-3, 1.0, 300.0]])
    got = depth_png16((z * norms).astype(np.float32), norms)
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, [[0, 2560, 65533, 0], [0, 0, 256, 0]])


def receding_sheet() -> DrawItem:
    """The plane x = 0.05 m seen from z = 0.2 to 2 m: its image is u in [cx + 0.19, cx + 1.95], so in the centre
    column a sample right of the pixel centre is covered while the centre (where the plane's range is infinite)
    is not."""
    c = 0.05
    vertices = np.array([[c, -0.1, 0.2], [c, 0.1, 0.2], [c, 0.1, 2.0], [c, -0.1, 2.0]])
    sheet = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], vertex_colors=np.tile([200, 120, 60, 255], (4, 1)),
                            process=False)
    return draw("test/render/receding-sheet", sheet)


def test_every_msaa_sample_range_lies_within_the_surface_it_covers(renderer):
    K = pinhole(W, H, 60.0)
    item = receding_sheet()
    _, range_m = renderer.samples(camera_view(K, W, H), [item], LIGHT, Sampling(msaa=4))
    seen = np.isfinite(range_m)
    assert np.any(seen[:, :, W // 2])
    # At most the far side of the sheet's bounding sphere (the true bound, 2.003 m, is a little tighter).
    assert range_m[seen].max() <= np.linalg.norm(item.mesh.centre) + item.mesh.radius


# --- open water -------------------------------------------------------------------------------------------------

WATER = WaterParams(
    beta_D=np.array([0.35, 0.08, 0.05]), beta_B=np.array([0.3, 0.07, 0.04]), B_inf=np.array([0.02, 0.19, 0.27])
)


def fronto_quad(K: np.ndarray, u: tuple[float, float], v: tuple[float, float], z: float) -> trimesh.Trimesh:
    """A flat rectangle at depth z (camera frame) whose image is exactly [u0, u1] x [v0, v1] (pixels)."""
    us, vs = np.array(u), np.array(v)
    x = (us - K[0, 2]) * z / K[0, 0]
    y = (vs - K[1, 2]) * z / K[1, 1]
    vertices = np.array([[x[0], y[0], z], [x[1], y[0], z], [x[1], y[1], z], [x[0], y[1], z]])
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    colours = np.tile(np.array([200, 120, 60, 255], np.uint8), (4, 1))
    return trimesh.Trimesh(vertices, faces, vertex_colors=colours, process=False)


def assert_veiling_light(pixels: np.ndarray, sampling: Sampling) -> None:
    """pixels (n, 3) float32 are float32(B_inf): each sample is exactly B_inf (transmission exactly 0, backscatter
    exactly 1), so one sample per pixel gives it bit for bit; summing n samples in float32 can round each partial
    sum, by at most (n - 1) * 2^-24 relative in all (tests/test_render_water.py checks exactness at every preset
    with veiling light whose multiples are exact)."""
    b_inf = np.broadcast_to(WATER.B_inf.astype(np.float32), pixels.shape)
    n = sampling.per_pixel
    if n == 1:
        np.testing.assert_array_equal(pixels, b_inf)
    else:
        np.testing.assert_allclose(pixels, b_inf, rtol=(n - 1) * 2.0**-24, atol=0)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_open_water_is_infinite_range_instance_zero_and_the_veiling_light(renderer, preset):
    K = pinhole(W, H, 60.0)
    # Edges on pixel boundaries: every sample of a pixel is either on the quad or open water.
    quad = fronto_quad(K, (2.5, 5.5), (1.5, 3.5), 5.0)
    result = renderer.render(
        camera_view(K, W, H), [draw("test/render/open-water-quad", quad, 7)],
        LIGHT, WATER, PRESETS[preset], Passes(clean=True, ids=True, range=True),
    )
    surface = np.zeros((H, W), bool)
    surface[2:4, 3:6] = True
    np.testing.assert_array_equal(np.isinf(result.range_m), ~surface)
    assert np.all(result.range_m[~surface] == np.inf)
    np.testing.assert_array_equal(result.instance, np.where(surface, 7, 0).astype(np.uint32))
    b_inf = WATER.B_inf.astype(np.float32)
    assert result.image.dtype == np.float32
    assert_veiling_light(result.image[~surface], PRESETS[preset])
    # The clean image has nothing there, and the quad itself is not the veiling light.
    assert np.all(result.clean[~surface] == 0)
    assert np.all(np.abs(result.image[surface] - b_inf).max(axis=-1) > 1e-3)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_an_empty_scene_is_all_open_water(renderer, preset):
    result = renderer.render(camera_view(K_WIDE, W, H), [], LIGHT, WATER, PRESETS[preset],
                             Passes(ids=True, range=True))
    assert np.all(result.range_m == np.inf) and np.all(result.instance == 0)
    assert_veiling_light(result.image.reshape(-1, 3), PRESETS[preset])


def test_range_is_the_same_with_or_without_water_and_at_any_sampling(renderer):
    """With edges on pixel boundaries every pixel centre hits the surface its samples hit, or none does. One sample a
    pixel takes range from the sample's depth, several from the centres' pass: the same to a few float32 ulps."""
    K = pinhole(W, H, 60.0)
    quad = fronto_quad(K, (2.5, 5.5), (1.5, 3.5), 5.0)
    item = draw("test/render/open-water-quad", quad, 7)
    view = camera_view(K, W, H)
    dry = renderer.render(view, [item], LIGHT, None, Sampling(msaa=1), Passes(range=True))
    wet = renderer.render(view, [item], LIGHT, WATER, Sampling(msaa=4), Passes(range=True))
    hit = np.isfinite(dry.range_m)
    np.testing.assert_array_equal(hit, np.isfinite(wet.range_m))
    assert hit.sum() == 6 and np.all(dry.range_m[~hit] == np.inf) and np.all(wet.range_m[~hit] == np.inf)
    np.testing.assert_allclose(dry.range_m[hit], wet.range_m[hit], rtol=1e-6)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_range_is_the_centre_where_it_hits_else_the_nearest_sample_and_inf_only_where_no_sample_hits(
    renderer, preset
):
    K = pinhole(W, H, 60.0)
    view = camera_view(K, W, H)
    # A sheet seen edge-on and a quad whose edges cut through pixels: pixels whose centre misses but samples hit.
    # A sliver 0.04 px wide through the centres of column 1: centres hit, (multisample) samples do not.
    sliver = fronto_quad(K, (0.98, 1.02), (0.5, H - 1.5), 5.0)
    items = [receding_sheet(), draw("test/render/off-grid-quad", fronto_quad(K, (2.2, 5.7), (1.3, 3.9), 5.0), 7),
             draw("test/render/sliver", sliver, 8)]
    sampling = PRESETS[preset]
    result = renderer.render(view, items, LIGHT, WATER, sampling, Passes(range=True))
    centre = renderer.geometry(view, items)[1]  # the pixel centres' pass
    _, samples = renderer.samples(view, items, LIGHT, sampling)  # (k, h, w): every sample of every pixel
    water = np.isinf(samples).all(axis=0)
    if sampling.per_pixel == 1:
        # The one sample is the centre: the frame's range is its own (from its depth), the centres' pass's to the
        # rasteriser's depth interpolation (measured: 4.5e-7 relative on llvmpipe, 4.2e-5 on an H100, both on the
        # sheet seen edge-on 0.4 m away).
        expected = samples[0]
        np.testing.assert_array_equal(np.isinf(centre), water)
        np.testing.assert_allclose(centre[~water], expected[~water], rtol=1e-4)
    else:
        expected = np.where(np.isfinite(centre) & ~water, centre, samples.min(axis=0))
    np.testing.assert_array_equal(result.range_m, expected)
    np.testing.assert_array_equal(np.isinf(result.range_m), water)
    assert_veiling_light(result.image[water], sampling)  # open water by the range is the veiling light
    assert np.all(np.isfinite(centre[1:H - 1, 1]))  # the sliver covers its column's centres
    if sampling.per_pixel > 1:  # the cases this rule is for occur here
        assert np.any(np.isinf(centre) & ~water) and np.any(np.isfinite(centre) & water)


# --- determinism ----------------------------------------------------------------------------------------------

ALL_OUTPUTS = {f"outputs.{k}": True for k in ("labels", "meta", "depth", "instance", "clean", "range")}


def test_a_frame_is_identical_bytes_when_rendered_again(render_session):
    spec = load_spec(EXAMPLE, {"camera.width": 48, "camera.height": 36, "noise.gaussian_sigma": 0.01, **ALL_OUTPUTS})
    first = render_session.frame_files(spec, 3)
    render_session.frame_files(spec, 4)  # other geometry in between: caches and GL state change
    again = render_session.frame_files(spec, 3)
    assert sorted(first) == sorted(again) == sorted(
        f"{d}/000003.{ext}" for d, ext in [("image_2", "png"), ("calib", "txt"), ("label_2", "txt"), ("meta", "json"),
                                           ("depth", "png"), ("instance", "png"), ("clean", "png"), ("range", "npy")]
    )
    for path in first:
        assert first[path] == again[path], path


def test_depth_file_is_the_range_file_as_z_depth(render_session):
    from PIL import Image

    spec = load_spec(EXAMPLE, {"camera.width": 48, "camera.height": 36, **ALL_OUTPUTS})
    files = render_session.frame_files(spec, 3)
    range_m = np.load(io.BytesIO(files["range/000003.npy"]))
    depth = np.asarray(Image.open(io.BytesIO(files["depth/000003.png"])))
    K = np.asarray(spec.camera.K())
    np.testing.assert_array_equal(depth, depth_png16(range_m, ray_norms(K, 48, 36)))
    instance = np.asarray(Image.open(io.BytesIO(files["instance/000003.png"])))
    assert not np.any(np.isnan(range_m)) and np.all(range_m > 0)
    # Every object pixel has a surface; the terrain (id 0) fills the lower part of the view.
    assert np.all(np.isfinite(range_m[instance > 0])) and np.any(instance > 0) and np.any(depth > 0)


# --- the water as the GL resolve pass applies it -----------------------------------------------------------------


@pytest.mark.parametrize("beta_b", [1e-4, 0.004, 0.05, 0.3, 2.0])
def test_gl_backscatter_matches_float64_expm1_on_the_samples_it_used(renderer, beta_b):
    """With black surfaces (J = 0) the image is B_inf (1 - exp(-beta_B z)) exactly as the shader computed it from
    each sample's stored range: compare with float64 expm1 on those ranges, 1e-6 relative (small beta*z included)."""
    K = pinhole(W, H, 90.0)
    mesh, pose = slab(np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0]), np.array([0.0, 0.0, 3.0]))
    mesh.visual.vertex_colors = np.tile([0, 0, 0, 255], (len(mesh.vertices), 1))
    item = draw("test/render/black-slab", mesh, pose=pose)
    b_inf = np.array([0.9, 0.5, 0.25])
    water = WaterParams(beta_D=np.full(3, 0.1), beta_B=np.full(3, beta_b), B_inf=b_inf)
    sampling = Sampling(msaa=4)
    _, R = renderer.samples(camera_view(K, W, H), [item], LIGHT, sampling)
    got = renderer.render(camera_view(K, W, H), [item], LIGHT, water, sampling, Passes()).image.astype(np.float64)
    assert np.isfinite(R).all()
    x = beta_b * R.astype(np.float64)  # (k, h, w): the float32 ranges the shader read, in float64
    expected = b_inf * (-np.expm1(-x)).mean(axis=0)[..., None]
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=0)


@settings(max_examples=100, deadline=None)
@given(axis=st.tuples(*[st.floats(-1.0, 1.0)] * 3), angle=st.floats(-np.pi, np.pi), mirror=st.booleans(),
       scale=st.one_of(st.sampled_from([5e-324, 1e-310, 1e-300, 1e-154, 2.0**-50, 2.0**50, 1e154, 1e300]),
                       st.floats(1e-300, 1e300)))
def test_the_normal_matrix_turns_normals_as_the_inverse_transpose_at_any_object_scale(axis, angle, mirror, scale):
    """targets.scale may be any float > 0: the normal matrix stays finite in float32 and turns normals as the
    rotation does; between 2^-50 and 2^50 it is the plain inverse transpose, bit for bit."""
    a = np.asarray(axis) if np.linalg.norm(axis) > 1e-3 else np.array([0.0, 0.0, 1.0])
    R = rotation_between(np.array([0.0, 0.0, 1.0]), a / np.linalg.norm(a)) @ np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    if mirror:
        R = R @ np.diag([-1.0, 1.0, 1.0])
    nrm = normal_matrix(R * scale)
    assert nrm.dtype == np.float32 and np.all(np.isfinite(nrm))
    if scale >= 1e-300:  # a normal float: the map keeps its rotation's every bit
        n = np.random.default_rng(0).normal(size=(16, 3))
        got = n @ nrm.T.astype(np.float64)
        want = n @ R.T
        np.testing.assert_allclose(got / np.linalg.norm(got, axis=1, keepdims=True),
                                   want / np.linalg.norm(want, axis=1, keepdims=True), atol=1e-6)
    if 2.0**-50 <= scale <= 2.0**50:
        assert np.array_equal(nrm, np.linalg.inv(R * scale).T.astype(np.float32))
