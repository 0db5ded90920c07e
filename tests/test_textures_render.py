"""Per-pixel textures on the GL path (worker.render.materials): a checker on a quad survives per pixel in the clean
image, the hazed image and its 8-bit codes, under random poses; a material with no images shades as no material;
normal maps turn the shading normal; the texture budget names the image that breaks it."""

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from test_render import camera_view, pinhole

from seasynth.service.errors import RenderError
from seasynth.worker.frame.formation import haze
from seasynth.worker.frame.srgb import decode_srgb8, encode_srgb8
from seasynth.worker.render import DrawItem, Image, Lighting, Material, Mesh, Passes, Sampling, WaterParams
from seasynth.worker.render.gl import GLRenderer
from seasynth.worker.render.materials import tangent_frames

W, H = 128, 96
K = pinhole(W, H, 60.0)
VIEW = camera_view(K, W, H)
AMBIENT_ONLY = Lighting(sun_dir_world=np.array([0.0, 0.0, -1.0]), sun_intensity=0.0, ambient=1.0)
WATER = WaterParams(beta_D=np.array([0.30, 0.12, 0.08]), beta_B=np.array([0.25, 0.10, 0.07]),
                    B_inf=np.array([0.05, 0.20, 0.30]))
UV = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)  # corners in order: (0, 0) top-left
FACES = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return ry @ rx @ rz


def quad(key: str, half: float, centre, R, material: Material | None, albedo=1.0) -> DrawItem:
    """A square 2 half metres across, its u along R's x and image up along -R's y (KITTI camera frame: y down),
    facing the camera (normal -R's z)."""
    local = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    v = (local @ R.T + centre).astype(np.float32)
    n = np.tile(-R[:, 2], (4, 1)).astype(np.float32)
    mesh = Mesh(key=key, vertices=v, normals=n, albedo=np.full((4, 3), albedo, np.float32), faces=FACES,
                radius=float(half * np.sqrt(2.0)), centre=np.asarray(centre, float), material=material,
                uv=UV if material is not None else None,
                tangents=tangent_frames(v, n, UV, FACES) if material is not None else None)
    return DrawItem(mesh=mesh, world_from_obj=np.eye(4), albedo_scale=np.ones(3, np.float32),
                    albedo_bias=np.zeros(3, np.float32), instance_id=1)


def pixel_uv(corners_px: np.ndarray, centre, R, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates (..., 2) and range (...) where the rays through pixel positions (..., 2) meet the quad's
    plane."""
    rays = np.concatenate([corners_px, np.ones(corners_px.shape[:-1] + (1,))], -1) @ np.linalg.inv(K).T
    normal, origin = R[:, 2], np.asarray(centre, float)
    t = (origin @ normal) / (rays @ normal)
    p = rays * t[..., None] - origin
    u = (p @ R[:, 0] + half) / (2 * half)
    v = (p @ R[:, 1] + half) / (2 * half)
    return np.stack([u, v], -1), t * np.linalg.norm(rays, axis=-1)


@pytest.fixture(scope="module")
def gl():
    with GLRenderer("egl") as r:
        yield r


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(checks=st.integers(2, 5), texels=st.integers(2, 6), seed=st.integers(0, 2**32 - 1),
       yaw=st.floats(-0.6, 0.6), pitch=st.floats(-0.6, 0.6), roll=st.floats(-np.pi, np.pi),
       distance=st.floats(1.0, 2.5))
def test_a_checker_survives_per_pixel_in_the_clean_and_hazed_image(gl, checks, texels, seed, yaw, pitch, roll,
                                                                    distance):
    assume(checks * texels <= 20)  # the texture magnified over the quad: its texels span more than a pixel
    rng = np.random.default_rng(seed)
    case = f"{checks}/{texels}/{seed}/{yaw!r}/{pitch!r}/{roll!r}/{distance!r}"  # GL caches go by key
    colours = rng.integers(0, 256, (checks, checks, 3)).astype(np.uint8)
    image = Image(f"test/checker/{case}", np.repeat(np.repeat(colours, texels, 0), texels, 1),
                  True, "checker")
    R, centre, half = rotation(yaw, pitch, roll), np.array([0.0, 0.0, distance]), 0.5
    item = quad(f"test/checker-quad/{case}", half, centre, R, Material(base=image))
    out = gl.render(VIEW, [item], AMBIENT_ONLY, WATER, Sampling(msaa=4, supersample=1), Passes(clean=True, range=True))
    codes = gl.render(VIEW, [item], AMBIENT_ONLY, WATER, Sampling(msaa=4, supersample=1), Passes(srgb8=True)).image

    # A pixel is checked where the filter footprints of all its samples map inside one check, between the centres
    # of its outer texels (bilinear filtering mixes nothing else there), with the texture magnified (no mip level
    # but the first). A sample lies within 0.5 px of the pixel centre and its footprint (the anisotropic filter's,
    # from the derivatives) reaches a pixel's width around it: the pixel's corners at +-1 px hold them all.
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    corners = np.stack([np.stack([xs + dx, ys + dy], -1) for dx in (-1.0, 1.0) for dy in (-1.0, 1.0)], -2)
    uv, _ = pixel_uv(corners, centre, R, half)
    centre_uv, rng_m = pixel_uv(np.stack([xs, ys], -1), centre, R, half)
    n_tex = checks * texels
    cell = np.floor(uv * checks).astype(int)
    same = np.all(cell == cell[..., :1, :], axis=(-2, -1)) & np.all((cell >= 0) & (cell < checks), axis=(-2, -1))
    margin = 0.5 / n_tex
    inner = np.all((uv * checks - cell) * (1.0 / checks) > margin, axis=(-2, -1)) & np.all(
        (cell + 1 - uv * checks) * (1.0 / checks) > margin, axis=(-2, -1))
    footprint = np.abs(uv.max(axis=-2) - uv.min(axis=-2)).max(axis=-1) * n_tex
    ok = same & inner & (footprint < 2.0)  # the corners span 2 px: under a texel a pixel
    assert ok.sum() >= 40  # the property is checked on many pixels, not a handful
    c = cell[..., 0, :]
    expected_J = decode_srgb8(colours[np.clip(c[..., 1], 0, checks - 1), np.clip(c[..., 0], 0, checks - 1)],
                              np.float64)
    # the sRGB decode of GL's samplers and ours agree to within a few 1e-4 (8-bit tables)
    np.testing.assert_allclose(out.clean[ok], expected_J[ok], atol=2e-3)
    expected_I = haze(expected_J, rng_m, WATER.beta_D, WATER.beta_B, WATER.B_inf)
    np.testing.assert_allclose(out.image[ok], expected_I[ok], atol=2e-3)
    assert np.abs(codes[ok].astype(int) - encode_srgb8(expected_I[ok]).astype(int)).max() <= 1
    # and the texture's pattern is there: at least two different check colours among the checked pixels
    assert len(np.unique(expected_J[ok].round(4), axis=0)) >= 2
    assert np.isfinite(centre_uv).all()


@pytest.mark.parametrize("mapping", ["uv", "triplanar"])
def test_a_material_without_images_shades_as_no_material(gl, mapping):
    R = rotation(0.3, -0.4, 0.2)
    plain = quad("test/plain-quad", 0.6, [0.1, 0.0, 2.0], R, None, albedo=0.6)
    blank = quad(f"test/blank-quad/{mapping}", 0.6, [0.1, 0.0, 2.0], R, Material(mapping=mapping), albedo=0.6)
    light = Lighting(sun_dir_world=np.array([0.3, -0.5, -0.8]) / np.linalg.norm([0.3, -0.5, -0.8]),
                     sun_intensity=0.8, ambient=0.3)
    a = gl.render(VIEW, [plain], light, None, Sampling(), Passes(clean=True)).clean
    b = gl.render(VIEW, [blank], light, None, Sampling(), Passes(clean=True)).clean
    assert (a > 0).sum() > 1000
    np.testing.assert_allclose(b, a, atol=1e-6)


def tilted_map(tilt) -> tuple[Image, np.ndarray]:
    """A constant normal map of the unit vector `tilt` (its texels and their decoded value)."""
    texel = np.round((np.asarray(tilt, float) + 1.0) / 2.0 * 255.0).astype(np.uint8)
    image = Image(f"test/normal-tilt/{texel.tolist()}", np.tile(texel, (4, 4, 1)), False, "tilted normal map")
    return image, texel / 255.0 * 2.0 - 1.0


TILTS = [(np.sin(0.6), 0.0, np.cos(0.6)), (0.0, np.sin(0.6), np.cos(0.6)), (0.4, -0.5, np.sqrt(1 - 0.41))]
SUN = np.array([0.5, -0.6, -0.6]) / np.linalg.norm([0.5, -0.6, -0.6])  # camera frame: towards the sun


def lit_centre(gl, item) -> float:
    light = Lighting(sun_dir_world=SUN, sun_intensity=1.0, ambient=0.0)
    return float(gl.render(VIEW, [item], light, None, Sampling(msaa=1), Passes(clean=True)).clean[H // 2, W // 2, 0])


@pytest.mark.parametrize("tilt", TILTS)
@pytest.mark.parametrize("mirrored", [False, True])
def test_a_normal_map_turns_the_shading_normal_as_its_texels_say(gl, tilt, mirrored):
    """x along +u, y towards the image's top (-v), z along the normal (glTF), whichever way the texture coordinates
    run (mirrored: u runs along -x, the tangent's w flips)."""
    image, m = tilted_map(tilt)
    item = quad(f"test/normal-quad/{tilt}/{mirrored}", 0.8, [0.0, 0.0, 2.0], np.eye(3), Material(normal=image))
    if mirrored:
        uv = UV[[1, 0, 3, 2]]
        mesh = Mesh(**{**item.mesh.__dict__, "key": item.mesh.key + "/m", "uv": uv,
                       "tangents": tangent_frames(item.mesh.vertices, item.mesh.normals, uv, FACES)})
        item = DrawItem(mesh, item.world_from_obj, item.albedo_scale, item.albedo_bias, item.instance_id)
    # camera frame: u along +x (mirrored: -x), v along +y (rows run down the quad), the normal -z (to the camera)
    T, up, N = np.array([-1.0 if mirrored else 1.0, 0, 0]), np.array([0, -1.0, 0]), np.array([0, 0, -1.0])
    n = m[0] * T + m[1] * up + m[2] * N
    n /= np.linalg.norm(n)
    # the sampler returns the map's 8-bit texels at 8-bit precision (llvmpipe: 0.984375 for 0.98464): 1/255 a
    # component moves the cosine by up to about 4e-3
    assert lit_centre(gl, item) == pytest.approx(max(n @ SUN, 0.0), abs=4e-3)
    assert abs(max(n @ SUN, 0.0) - max(-SUN[2], 0.0)) > 0.05  # and differs from the unmapped shading


# (object-frame axes of a quad's u, t and normal under triplanar mapping, and a pose turning its normal to the camera)
PLANES = {
    "z": (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, -1.0]), np.eye(3)),
    "x": (np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0]),
          np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]])),  # object x -> camera -z
}


@pytest.mark.parametrize("tilt", TILTS)
@pytest.mark.parametrize("plane", PLANES)
def test_a_triplanar_normal_map_turns_the_normal_as_its_texels_say(gl, tilt, plane):
    """On a face along an object axis, the projection's u and t (x: z, y; z: x, y) take the map's x and, up the
    image, -t its y; the object's pose carries the result to the camera."""
    image, m = tilted_map(tilt)
    U, V, N, R = PLANES[plane]
    corners = np.array([-U - V, U - V, U + V, -U + V]) * 0.8 + N * 0.0
    v = corners.astype(np.float32)
    mesh = Mesh(key=f"test/triplanar-quad/{plane}/{tilt}", vertices=v, normals=np.tile(N, (4, 1)).astype(np.float32),
                albedo=np.ones((4, 3), np.float32), faces=FACES, radius=1.2, centre=np.zeros(3),
                material=Material(normal=image, mapping="triplanar"))
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, [0.0, 0.0, 2.0]
    item = DrawItem(mesh, pose, np.ones(3, np.float32), np.zeros(3, np.float32), 1)
    n = R @ (m[0] * U - m[1] * V + m[2] * N)
    n /= np.linalg.norm(n)
    assert (R @ N)[2] < 0  # the face looks at the camera
    assert lit_centre(gl, item) == pytest.approx(max(n @ SUN, 0.0), abs=4e-3)


def test_a_texture_over_the_budget_is_refused_naming_it():
    big = Image("test/big", np.zeros((512, 512, 3), np.uint8), True, "seabed.png")
    item = quad("test/big-quad", 0.5, [0.0, 0.0, 2.0], np.eye(3), Material(base=big))
    with GLRenderer("egl", texture_budget_bytes=2**20) as r, pytest.raises(RenderError, match="seabed.png"):
        r.render(VIEW, [item], AMBIENT_ONLY, None, Sampling(msaa=1), Passes())


def test_each_face_group_is_drawn_with_its_own_material(gl):
    """A mesh of two face ranges, one with a red texture and one with none, shades each range as its own; the ids
    pass draws the whole mesh."""
    red = Image("test/red", np.tile(np.array([255, 0, 0], np.uint8), (2, 2, 1)), True, "red")
    whole = quad("test/groups-whole", 0.8, [0.0, 0.0, 2.0], np.eye(3), Material(base=red), albedo=0.5)
    mesh = Mesh(**{**whole.mesh.__dict__, "key": "test/groups", "groups": ((0, 1, Material(base=red)), (1, 1, None))})
    item = DrawItem(mesh=mesh, world_from_obj=np.eye(4), albedo_scale=np.ones(3, np.float32),
                    albedo_bias=np.zeros(3, np.float32), instance_id=7)
    out = gl.render(VIEW, [item], AMBIENT_ONLY, None, Sampling(msaa=1), Passes(clean=True, ids=True))
    # faces (0, 1, 2) and (0, 2, 3) of corners (-x, -y), (+x, -y), (+x, +y), (-x, +y) split along the diagonal
    # y = x (camera frame): above it (image top right, y < x) face 0, below it face 1
    top_right, bottom_left = out.clean[H // 2 - 15, W // 2 + 15], out.clean[H // 2 + 15, W // 2 - 15]
    np.testing.assert_allclose(top_right, [0.5, 0.0, 0.0], atol=2e-3)  # red texture times the vertex albedo
    np.testing.assert_allclose(bottom_left, [0.5, 0.5, 0.5], atol=1e-6)  # the vertex albedo alone
    assert (out.instance[H // 2 - 15, W // 2 + 15], out.instance[H // 2 + 15, W // 2 - 15]) == (7, 7)


def tiled_quad(key: str, texels: np.ndarray, repeats: float, normal_scale: float = 1.0) -> DrawItem:
    """quad() with the normal map `texels` repeated `repeats` times along u and v."""
    item = quad(key, 0.8, [0.0, 0.0, 2.0], np.eye(3),
                Material(normal=Image(key, texels, False, key), normal_scale=normal_scale))
    uv = UV * repeats
    mesh = Mesh(**{**item.mesh.__dict__, "uv": uv, "tangents": tangent_frames(item.mesh.vertices,
                                                                               item.mesh.normals, uv, FACES)})
    return DrawItem(mesh, item.world_from_obj, item.albedo_scale, item.albedo_bias, item.instance_id)


@pytest.mark.parametrize("tilt", [0.3, 0.6])
def test_relief_finer_than_a_pixel_shades_as_the_mean_of_its_normals(gl, tilt):
    """Stripes one texel wide of normals tilted +-tilt about the tangent, many texels to a pixel: a Lambertian
    surface's mean shading over the pixel is the mean normal's (length cos tilt, along the surface normal) dot the
    sun, cos tilt times the flat surface's; renormalised, the mipmapped mean would shade as flat."""
    s, c = np.sin(tilt), np.cos(tilt)
    stripes = np.stack([(s, 0.0, c), (-s, 0.0, c)])[np.arange(64) % 2]  # along u
    texels = np.round((np.tile(stripes[None], (64, 1, 1)) + 1.0) / 2.0 * 255.0).astype(np.uint8)
    flat_texels = np.full((64, 64, 3), [128, 128, 255], np.uint8)
    # 4096 texels across the quad's ~100 pixels: every lookup averages dozens of stripes
    relief = lit_centre(gl, tiled_quad(f"test/relief/{tilt}", texels, 64.0))
    flat = lit_centre(gl, tiled_quad("test/relief/flat", flat_texels, 64.0))
    decoded = texels[0, :2] / 255.0 * 2.0 - 1.0  # the two texels as the sampler reads them
    mean_length = float(np.linalg.norm(decoded.mean(axis=0)))  # cos tilt to 8-bit precision
    # 1e-2: the shader counts lengths from 253/255 (8-bit unit normals are up to ~2/255 short), so a length of ~0.9
    # reads 0.8% long
    assert relief / flat == pytest.approx(mean_length, rel=1e-2)
    d = flat_texels[0, 0] / 255.0 * 2.0 - 1.0  # 128 reads 0.0039: the "flat" map leans a little
    n = d[0] * np.array([1.0, 0.0, 0.0]) + d[1] * np.array([0.0, -1.0, 0.0]) + d[2] * np.array([0.0, 0.0, -1.0])
    assert flat == pytest.approx(n @ SUN / np.linalg.norm(n), abs=2e-3)
    assert mean_length < 0.96  # the relief darkens the surface measurably


@pytest.mark.parametrize("scale", [0.0, 0.5])
def test_a_weaker_normal_map_darkens_its_relief_less(gl, scale):
    """normal_scale s tilts each texel s times as far: the relief's darkening 1 - cos(tilt) becomes about
    1 - cos(s tilt) (s^2 as large for small tilts); at 0 the surface shades as flat."""
    tilt = 0.4
    stripes = np.stack([(np.sin(tilt), 0.0, np.cos(tilt)), (-np.sin(tilt), 0.0, np.cos(tilt))])[np.arange(64) % 2]
    texels = np.round((np.tile(stripes[None], (64, 1, 1)) + 1.0) / 2.0 * 255.0).astype(np.uint8)
    flat_texels = np.full((64, 64, 3), [128, 128, 255], np.uint8)
    relief = lit_centre(gl, tiled_quad(f"test/relief-scaled/{scale}", texels, 64.0, scale))
    flat = lit_centre(gl, tiled_quad(f"test/relief-scaled-flat/{scale}", flat_texels, 64.0, scale))
    # 3e-3: lengths are read from 253/255, 0.8% long (cos 0.4 reads 0.928, not 0.921), which leaves a quarter of
    # 7e-3 at s = 0.5 (2.4e-3 measured on llvmpipe)
    assert relief / flat == pytest.approx(np.cos(scale * tilt), abs=3e-3)

