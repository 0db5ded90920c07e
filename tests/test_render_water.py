"""Tests of the water as the GL path applies it (surface pass range, resolve pass haze): the model per pixel against
analytic ranges, and its hard cases exactly, on the shaders that make every image."""

import numpy as np
import pytest
import trimesh
from test_render import LIGHT, camera_view, draw, fronto_quad, pinhole, pixel_aligned_plane, rays

from seasynth.worker.frame.function import PRESETS
from seasynth.worker.render import Lighting, Passes, WaterParams

# A 120-degree view: the corner rays are about 2.3 times as long as the central one, so range and z-depth differ
# by a factor the image cannot hide.
W, H = 33, 25
K_WIDE = pinhole(W, H, 120.0)
# Few significant bits: k * B_inf is exact in float32 for k <= 16, so a pixel's average of samples that are each
# exactly B_inf is exactly B_inf at every preset (other values can round in the sum, by under 16 ulps).
B_INF = np.array([1 / 16, 3 / 16, 5 / 16])
# Backscatter optical depths of 0.1 to 24 across the planes below; blue's (0.1 to 2.4) keeps range recoverable.
WATER = WaterParams(beta_D=np.array([0.4, 0.1, 0.05]), beta_B=np.array([0.01, 0.004, 0.001]), B_inf=B_INF)
# The sun behind the camera: a plane facing it is lit well above the ambient term.
FRONT_LIGHT = Lighting(sun_dir_world=np.array([0.0, -0.6, -0.8]), sun_intensity=0.8, ambient=0.2)
NORMALS = {
    "fronto-parallel": np.array([0.0, 0.0, 1.0]),
    "oblique": np.array([0.35, -0.25, 1.0]) / np.linalg.norm([0.35, -0.25, 1.0]),
}
# Presets that shade J once a pixel (at its centre), so a plane's clean pixel is every sample's J; water is applied
# at each sample's own range (from its depth) at every preset.
CENTRE_SHADED = [name for name, s in PRESETS.items() if s.msaa * s.supersample**2 == 1 or not s.per_sample_shading]


def plane_range(normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(H, W) float64 metres: range along each pixel-centre ray to the plane through `point` with unit `normal`."""
    d = rays(K_WIDE, W, H)
    return (normal @ point) / (d @ normal) * np.linalg.norm(d, axis=-1)


def sample_rays(renderer, preset: str) -> np.ndarray:
    """(H, W, k, 3) float64: K^-1 [u, v, 1] through each of a pixel's k samples, at the positions the renderer's
    multisample pattern puts them (read after a render at that preset)."""
    s = PRESETS[preset]
    pos = renderer.sample_positions[s.msaa].astype(np.float64)
    ss = s.supersample
    offsets = np.array([((dx + x) / ss - 0.5, (dy + y) / ss - 0.5)
                        for dy in range(ss) for dx in range(ss) for x, y in pos])  # image pixels from the centre
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    uv1 = np.stack([u[..., None] + offsets[:, 0], v[..., None] + offsets[:, 1], np.ones((H, W, len(offsets)))], -1)
    return uv1 @ np.linalg.inv(K_WIDE).T


def sample_plane_range(renderer, preset: str, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(H, W, k) float64 metres: range to the plane along each sample's ray (sample_rays)."""
    d = sample_rays(renderer, preset)
    return (normal @ point) / (d @ normal) * np.linalg.norm(d, axis=-1)


def ray_cast(mesh: trimesh.Trimesh, directions: np.ndarray) -> np.ndarray:
    """(n,) float64 metres: distance from the origin along each of `directions` (n, 3) to the nearest triangle of
    `mesh` (camera frame), +inf where none: each ray against each triangle's plane, kept where it lands inside."""
    tris = mesh.triangles
    d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    ray = np.repeat(np.arange(len(d)), len(tris))
    tri = np.tile(np.arange(len(tris)), len(d))
    points, valid, t = trimesh.intersections.planes_lines(
        tris[tri, 0], mesh.face_normals[tri], np.zeros((len(ray), 3)), d[ray], return_distance=True
    )
    inside = np.all(trimesh.triangles.points_to_barycentric(tris[tri[valid]], points) >= -1e-9, axis=1) & (t > 0)
    out = np.full(len(d), np.inf)
    np.minimum.at(out, ray[valid][inside], t[inside])
    return out


def coloured_plane(key: str, normal: np.ndarray, rgb: tuple[int, int, int], distance_m: float = 100.0):
    """The plane filling the view (corners on the sub-pixel grid: see pixel_aligned_plane), its draw item and mesh."""
    mesh = pixel_aligned_plane(K_WIDE, W, H, normal, np.array([0.0, 0.0, distance_m]), rgb)
    return draw(f"test/render-water/{key}", mesh), mesh


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("orientation", sorted(NORMALS))
def test_backscatter_of_a_black_plane_follows_the_true_range_across_a_120_degree_view(renderer, orientation, preset):
    """J = 0, so the image is the mean over a pixel's samples of B_inf (1 - exp(-beta_B z)), z each sample's range
    (from its reversed float depth). Float32 depth (the plane's corners on the sub-pixel grid) and GLSL exp keep it
    within 1e-5 relative of float64 on the analytic range; z-depth instead of range is off by tens of percent."""
    normal = NORMALS[orientation]
    item, mesh = coloured_plane(f"black/{orientation}", normal, (0, 0, 0))
    result = renderer.render(camera_view(K_WIDE, W, H), [item], LIGHT, WATER, PRESETS[preset], Passes())
    true_range = plane_range(normal, np.array([0.0, 0.0, 100.0]))
    at_samples = sample_plane_range(renderer, preset, normal, np.array([0.0, 0.0, 100.0]))
    expected = (WATER.B_inf * -np.expm1(-WATER.beta_B * at_samples[..., None])).mean(axis=2)
    assert result.image.dtype == np.float32
    np.testing.assert_allclose(result.image, expected, rtol=1e-5, atol=0)

    # The range the image was hazed with, recovered from its best-conditioned channel, matches a trimesh ray cast of
    # the samples' rays (independent of the analytic formula) within 1e-3 at the four corners and the centre.
    rows = np.array([0, 0, H - 1, H - 1, H // 2])
    cols = np.array([0, W - 1, 0, W - 1, W // 2])
    sample_dirs = sample_rays(renderer, preset)[rows, cols]  # (5, k, 3)
    cast = ray_cast(mesh, sample_dirs.reshape(-1, 3)).reshape(sample_dirs.shape[:2])
    np.testing.assert_allclose(cast, at_samples[rows, cols], rtol=1e-9)
    c, b = 2, WATER.beta_B[2]
    from_image = -np.log1p(-result.image[rows, cols, c].astype(np.float64) / WATER.B_inf[c]) / b
    from_cast = -np.log1p(np.expm1(-b * cast).mean(axis=1)) / b  # the one range whose haze is the samples' mean
    np.testing.assert_allclose(from_image, from_cast, rtol=1e-3)
    assert true_range[0, 0] > 2 * true_range[H // 2, W // 2]


@pytest.mark.parametrize("preset", CENTRE_SHADED)
@pytest.mark.parametrize("orientation", sorted(NORMALS))
def test_a_lit_plane_is_the_whole_model_per_pixel(renderer, orientation, preset):
    """The mean over a pixel's samples of J exp(-beta_D z) + B_inf (1 - exp(-beta_B z)), J the clean image (shaded
    once a pixel at these presets) and z each sample's analytic range, within 1e-5 relative. Optical depths stay
    under 2.4, so float32 range (1e-6) and GLSL exp keep the transmission within 3e-6; an error of 2% in its
    exponent is 2e-3 at the centre and more towards the corners."""
    normal = NORMALS[orientation]
    water = WaterParams(beta_D=np.array([0.01, 0.006, 0.004]), beta_B=np.array([0.008, 0.005, 0.003]), B_inf=B_INF)
    item, _ = coloured_plane(f"grey/{orientation}", normal, (200, 150, 100), distance_m=10.0)
    result = renderer.render(camera_view(K_WIDE, W, H), [item], FRONT_LIGHT, water, PRESETS[preset],
                             Passes(clean=True))
    J = result.clean.astype(np.float64)
    z = sample_plane_range(renderer, preset, normal, np.array([0.0, 0.0, 10.0]))[..., None]  # (H, W, k, 1)
    direct = J * np.exp(-water.beta_D * z).mean(axis=2)
    expected = direct + (water.B_inf * -np.expm1(-water.beta_B * z)).mean(axis=2)
    assert np.all(J > 0.02)
    # Both terms count: the direct signal is most of the central pixel, and the backscatter is there everywhere.
    centre = (H // 2, W // 2)
    assert np.all(direct[centre] / expected[centre] > 0.5) and np.all(expected - direct > 1e-3)
    np.testing.assert_allclose(result.image, expected, rtol=1e-5, atol=0)


# --- hard cases -------------------------------------------------------------------------------------------------

# W_SMALL x H_SMALL pixels; the quad's edges lie on pixel boundaries, so every sample of a pixel is either on the
# quad or open water, at every preset.
W_SMALL, H_SMALL = 9, 7
K_SMALL = pinhole(W_SMALL, H_SMALL, 60.0)
QUAD_PIXELS = (slice(2, 4), slice(3, 6))


def quad_frame(renderer, water: WaterParams, preset: str):
    quad = fronto_quad(K_SMALL, (2.5, 5.5), (1.5, 3.5), 5.0)
    item = draw("test/render-water/quad", quad, 7)
    result = renderer.render(camera_view(K_SMALL, W_SMALL, H_SMALL), [item], LIGHT, water, PRESETS[preset],
                             Passes(clean=True, range=True))
    open_water = np.ones((H_SMALL, W_SMALL), bool)
    open_water[QUAD_PIXELS] = False
    np.testing.assert_array_equal(np.isinf(result.range_m), open_water)
    return result, open_water


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize(
    "beta_D, beta_B",
    [
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        ((0.0, 0.3, 0.2), (0.0, 0.0, 0.25)),  # red clear; green only attenuates; blue both
        ((0.3, 0.0, 0.0), (0.0, 0.25, 0.0)),  # red only attenuates; green only scatters; blue clear
    ],
    ids=["all-clear", "red-clear", "blue-clear"],
)
def test_zero_beta_channels_are_the_clean_image_and_open_water_per_channel_is_exact(renderer, preset, beta_D, beta_B):
    """Per channel: beta_D = beta_B = 0 gives the clean image bit for bit (surface and open water); open water is
    exactly float32(B_inf) where beta_B > 0 and exactly 0 where beta_B = 0 (no backscatter, whatever beta_D)."""
    beta_D, beta_B = np.array(beta_D), np.array(beta_B)
    water = WaterParams(beta_D=beta_D, beta_B=beta_B, B_inf=B_INF)
    result, open_water = quad_frame(renderer, water, preset)
    clear = (beta_D == 0) & (beta_B == 0)
    np.testing.assert_array_equal(result.image[..., clear], result.clean[..., clear])
    veil = np.where(beta_B > 0, B_INF.astype(np.float32), np.float32(0.0))
    np.testing.assert_array_equal(result.image[open_water], np.broadcast_to(veil, (np.count_nonzero(open_water), 3)))
    assert np.all(result.clean[open_water] == 0)
    # Where a channel attenuates, the quad is dimmer than in air.
    attenuated = beta_D > 0
    assert np.all(result.image[QUAD_PIXELS][..., attenuated & (beta_B == 0)] <
                  result.clean[QUAD_PIXELS][..., attenuated & (beta_B == 0)])


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_a_surface_at_a_tiny_range_is_the_clean_image_to_float32_precision(renderer, preset):
    """At z = 1e-8 m, beta z < 1e-8: the model's I differs from J by less than float32 resolves, so the image is
    the clean image to float32 precision: 4 ulps (GLSL allows exp 3 ulps, so exp(-1e-9) may be 1 - 2^-24; the
    average of the samples can round once more)."""
    z = 1e-8
    quad = fronto_quad(K_SMALL, (-0.5, W_SMALL - 0.5), (-0.5, H_SMALL - 0.5), z)  # fills the view
    water = WaterParams(beta_D=np.array([0.4, 0.1, 0.05]), beta_B=np.array([0.3, 0.08, 0.04]), B_inf=B_INF)
    result = renderer.render(camera_view(K_SMALL, W_SMALL, H_SMALL, near=z / 10, far=z * 10),
                             [draw("test/render-water/tiny-range", quad)], LIGHT, water, PRESETS[preset],
                             Passes(clean=True, range=True))
    assert np.all(np.isfinite(result.range_m)) and result.range_m.max() < 2 * z
    assert np.all(result.clean > 0)
    np.testing.assert_allclose(result.image, result.clean, rtol=4 * 2.0**-23, atol=0)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_huge_optical_depth_is_the_veiling_light_exactly_with_no_nan(renderer, preset):
    """beta z of 1e6, 5e3 and 700 on the quad at 5 m (the shaders' float32 path, not numpy's): transmission
    underflows to nothing and backscatter is exactly 1, so every pixel, quad and open water alike, is exactly
    float32(B_inf) — no NaN, no inf, no residue of the surface colour."""
    beta = np.array([2e5, 1e3, 140.0])
    result, _ = quad_frame(renderer, WaterParams(beta_D=beta, beta_B=beta, B_inf=B_INF), preset)
    assert np.all(np.isfinite(result.image))
    assert np.all(result.clean[QUAD_PIXELS] > 0.005)  # there is a surface colour to lose
    np.testing.assert_array_equal(result.image, np.broadcast_to(B_INF.astype(np.float32), result.image.shape))
