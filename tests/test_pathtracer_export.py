"""The Mitsuba reference renderer: exported geometry and camera match an independent ray cast; radiometry is exact."""

import dataclasses
import importlib.util

import numpy as np
import pytest

if importlib.util.find_spec("mitsuba") is None:  # only a missing Mitsuba skips; a missing libLLVM fails loudly
    pytest.skip("mitsuba is not installed (pip install -e '.[bench]')", allow_module_level=True)

trimesh = pytest.importorskip("trimesh")

from seasynth.bench import pathtracer as pt  # noqa: E402

W, H = 32, 24
F = 28.0  # fx = fy, pixels


@pytest.fixture(scope="module", autouse=True)
def _libllvm():
    pt.use_libllvm()  # before anything imports drjit


def world_from_cam(eye, target, up) -> np.ndarray:
    """(4, 4) float64 KITTI camera (x right, y down, z forward) to world."""
    z = np.subtract(target, eye, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def pt_mesh(mesh, instance_id: int, albedo: float) -> pt.PTMesh:
    n = len(mesh.vertices)
    return pt.PTMesh(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32),
                     np.full((n, 3), albedo, np.float32), instance_id)


def flat_scene(*, z_cam=2.0, surface_z=4.0, sigma_a=(0.0, 0.0, 0.0), sun=(0.0, 0.0, 0.0), sky=(0.0, 0.0, 0.0),
               lamps=()) -> pt.PTScene:
    """A white horizontal 100 m plane at z = 0, seen straight down from height z_cam; sun 30 deg off the zenith."""
    plane = trimesh.Trimesh([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], [[0, 1, 2], [0, 2, 3]])
    K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])
    return pt.PTScene(
        meshes=(pt_mesh(plane, 0, 1.0),), K=K, width=W, height=H,
        world_from_cam=world_from_cam([0.0, 0.0, z_cam], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        sigma_a=np.array(sigma_a), sigma_s=np.zeros(3), g=0.9, surface_z=surface_z,
        sun_dir_world=np.array([np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))]),
        sun_irradiance_rgb=np.array(sun), sky_radiance_rgb=np.array(sky), lamps=tuple(lamps))


def view_distance(scene: pt.PTScene, sub: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, sub*sub) float64 metres from the camera to the z = 0 plane along sub x sub rays spread over each pixel
    (the centre when sub = 1), and (H, W, sub*sub) float64 cos of each ray's angle to straight down."""
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    v, u, dv, du = np.meshgrid(np.arange(H), np.arange(W), offsets, offsets, indexing="ij")
    rays = np.linalg.solve(scene.K, np.stack([(u + du).ravel(), (v + dv).ravel(), np.ones(u.size)]))
    cos = (rays[2] / np.linalg.norm(rays, axis=0)).reshape(H, W, sub * sub)
    return scene.world_from_cam[2, 3] / cos, cos


def assert_mean_ratio_one(ratio: np.ndarray, max_se: float, bias: float = 0.0) -> None:
    """The mean of (n, c) per-pixel ratios is 1 within 5 standard errors (from the pixels' spread) plus `bias`."""
    se = ratio.std(axis=0, ddof=1) / np.sqrt(len(ratio))
    assert np.all(se < max_se), se  # the check is only strong when the noise is small
    np.testing.assert_array_less(np.abs(ratio.mean(axis=0) - 1.0), 5.0 * se + bias)


def test_instance_ids_match_an_independent_ray_cast():
    rng = np.random.default_rng(5)
    terrain = trimesh.Trimesh([[-3, -3, 0], [3, -3, 0], [3, 3, 0.4], [-3, 3, 0.4]], [[0, 1, 2], [0, 2, 3]])
    box = trimesh.creation.box(extents=[0.6, 0.5, 0.7])
    box.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0, 0, 1]))
    box.apply_translation([-0.7, 0.2, 0.45])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.45)
    sphere.apply_translation([0.8, -0.3, 0.55])
    # Off-centre principal point and a tilted camera exercise the whole camera export.
    K = np.array([[F, 0.0, 14.2], [0.0, F, 12.7], [0.0, 0.0, 1.0]])
    scene = pt.PTScene(
        meshes=(pt_mesh(terrain, 0, 0.5), pt_mesh(box, 1, 0.7), pt_mesh(sphere, 2, 0.3)), K=K, width=W, height=H,
        world_from_cam=world_from_cam([0.3, -2.2, 2.6], [0.0, 0.0, 0.2], [0.0, 0.0, 1.0]),
        sigma_a=rng.uniform(0, 0.2, 3), sigma_s=rng.uniform(0, 0.2, 3), g=0.9, surface_z=5.0,
        sun_dir_world=np.array([0.0, 0.0, 1.0]), sun_irradiance_rgb=np.ones(3), sky_radiance_rgb=np.ones(3))
    ids = pt.render_ids(scene)

    both = trimesh.util.concatenate([terrain, box, sphere])
    face_ids = np.repeat([0, 1, 2], [len(terrain.faces), len(box.faces), len(sphere.faces)])

    def cast(du: float, dv: float) -> np.ndarray:
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        rays = np.linalg.solve(K, np.stack([(u + du).ravel(), (v + dv).ravel(), np.ones(u.size)]))
        dirs = (scene.world_from_cam[:3, :3] @ rays).T
        tri = both.ray.intersects_first(np.repeat(scene.world_from_cam[None, :3, 3], len(dirs), 0), dirs)
        return np.where(tri >= 0, face_ids[np.maximum(tri, 0)], 0).reshape(H, W)

    # Mitsuba builds rays in float32 (~1e-5 px); a centre ray within 1e-3 px of a silhouette may go either way.
    ids_agree_off_silhouettes(ids, cast)
    counts = np.bincount(ids.ravel())
    assert ids.dtype == np.uint32 and len(counts) == 3 and counts.min() >= 20, counts


def test_sun_on_a_white_plane_in_clear_water_is_exact():
    E = np.array([1.0, 2.0, 3.0])
    image = pt.render(flat_scene(sun=E), spp=2)
    # Delta light, sampled by NEE with MIS weight 1: every sample is exactly E*cos/pi; bounces escape to a black sky.
    np.testing.assert_allclose(image, np.broadcast_to(E * np.cos(np.radians(30.0)) / np.pi, image.shape), rtol=2e-5)


def test_a_sphere_is_lambertian_with_its_albedo_and_hides_the_plane_behind_it():
    """A sphere of albedo 0.5 under the camera: where its top faces the camera it has radiance 0.5 E cos/pi (the
    mean of the four pixels round the centre ray, whose normals tilt symmetrically); far from it, the plane's."""
    E = np.array([1.0, 2.0, 3.0])
    spheres = pt.PTSpheres(np.array([[0.0, 0.0, 0.6]]), np.array([0.3]), np.array([[0.5, 0.5, 0.5]], np.float32))
    scene = dataclasses.replace(flat_scene(sun=E), spheres=spheres)
    image = pt.render(scene, spp=64, seed=4)
    plane = E * np.cos(np.radians(30.0)) / np.pi
    centre = image[H // 2 - 1: H // 2 + 1, W // 2 - 1: W // 2 + 1].reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(centre, 0.5 * plane, rtol=0.02)
    np.testing.assert_allclose(image[0, 0], plane, rtol=2e-5)
    assert pt.render_ids(scene).max() == 0  # spheres are not instances


def test_absorbing_water_attenuates_the_view_ray_and_the_sun_ray():
    E, a, depth = np.array([1.0, 2.0, 3.0]), np.array([0.02, 0.05, 0.1]), 4.0
    scene = flat_scene(sigma_a=a, sun=E, surface_z=depth)
    image = pt.render(scene, spp=256, seed=3)
    d, _ = view_distance(scene)
    cos_sun = np.cos(np.radians(30.0))
    expected = E * cos_sun / np.pi * np.exp(-a * (d + depth / cos_sun))  # (H, W, 3) via d's singleton axis
    # Free-flight sampling makes each sample 0 or a rescaled value: check the mean ratio statistically.
    assert_mean_ratio_one((image / expected).reshape(-1, 3), max_se=0.004)


def test_sky_is_a_cone_about_world_up():
    L = np.array([0.5, 1.0, 2.0])
    image = pt.render(flat_scene(sky=L), spp=64, seed=1)
    # An upward-facing white plane under a uniform cone of half angle c receives pi*L*sin(c)^2.
    expected = L * np.sin(np.radians(48.6)) ** 2
    # bias: the lat-long map's one-row-wide cone edge (Mitsuba's sampling leaves ~2/ENV_ROWS, measured 3e-4).
    assert_mean_ratio_one((image / expected).reshape(-1, 3), max_se=0.002, bias=5.0 / pt.ENV_ROWS)


def test_spot_lamp_follows_mitsubas_linear_falloff():
    intensity, cutoff, beam = np.array([2.0, 1.0, 0.5]), 30.0, 18.0
    lamp = pt.PTLamp(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0]), cutoff, beam, intensity)
    scene = flat_scene(lamps=[lamp])
    spp = 64
    image = pt.render(scene, spp=spp, seed=2)
    d, cos = view_distance(scene, sub=16)  # the lamp sits at the camera: the same rays, 16 x 16 over each pixel
    falloff = np.clip((cutoff - np.degrees(np.arccos(cos))) / (cutoff - beam), 0.0, 1.0)
    per_ray = intensity * (falloff * cos / (np.pi * d**2))[..., None]  # (H, W, 256, 3) W/(m^2 sr)
    lo, hi = falloff.min(axis=2), falloff.max(axis=2)
    regimes = [lo == 1, (hi < 1) & (lo > 0), hi == 0]
    assert all(r.sum() >= 20 for r in regimes)  # full beam, the linear ramp, and dark pixels are all checked
    # A sample's value is exact given its position in the pixel (delta light), so the pixel's Monte-Carlo error is
    # the spread of per_ray over the pixel / sqrt(spp); 1e-3 covers the 16 x 16 quadrature and float32.
    tolerance = 5.0 * per_ray.std(axis=2) / np.sqrt(spp) + 1e-3 * per_ray.max()
    np.testing.assert_array_less(np.abs(image - per_ray.mean(axis=2)), tolerance)


@pytest.mark.parametrize("exact_nee", [False, True])
def test_a_lamp_housing_keeps_the_light_that_leaves_it_in_absorbing_water(exact_nee):
    """A water-free sphere round the lamp (which bounds multiply scattered fireflies in the references) with the
    lamp's intensity scaled by exp(-a R): in water that only absorbs, the plane gets what it gets without a housing,
    I falloff cos / (pi d^2) exp(-a d) on the lamp's leg and exp(-a d) on the view's; with Mitsuba's volpath and
    with exact shadow-ray transmittance (bench/pathtracer_integrator.py)."""
    intensity, cutoff, beam, a = np.array([2.0, 1.0, 0.5]), 30.0, 18.0, np.array([0.05, 0.1, 0.2])
    lamp = pt.PTLamp(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0]), cutoff, beam, intensity)
    scene = flat_scene(lamps=[lamp], sigma_a=a)
    image = pt.render(scene, spp=256, seed=4, lamp_housing_m=0.3, exact_nee=exact_nee)
    d, cos = view_distance(scene)
    falloff = np.clip((cutoff - np.degrees(np.arccos(cos))) / (cutoff - beam), 0.0, 1.0)
    expected = intensity * (falloff * cos / (np.pi * d**2)) * np.exp(-2.0 * a * d)
    lit = falloff[..., 0] == 1.0
    assert lit.sum() >= 20
    assert_mean_ratio_one((image[lit] / expected[lit]), max_se=0.01)


def test_rendering_several_seeds_at_once_gives_each_seed_s_own_render():
    scene = flat_scene(sigma_a=(0.1, 0.1, 0.1), sun=(1.0, 1.0, 1.0), sky=(0.2, 0.2, 0.2))
    images = pt.render_seeds(scene, 3, (5, 6))
    assert all(np.array_equal(image, pt.render(scene, 3, seed=s)) for image, s in zip(images, (5, 6)))
    assert not np.array_equal(*images)


def test_a_flat_port_traced_by_mitsubas_dielectrics_bends_rays_as_the_camera_model_does():
    from seasynth.service.camera_model import CameraModel

    terrain = trimesh.Trimesh([[-3, -3, 0], [3, -3, 0], [3, 3, 0.4], [-3, 3, 0.4]], [[0, 1, 2], [0, 2, 3]])
    spheres = [trimesh.creation.icosphere(subdivisions=3, radius=r).apply_translation(c)
               for r, c in ((0.45, [0.8, -0.3, 0.55]), (0.3, [-0.6, 0.4, 0.5]))]
    K = np.array([[F, 0.0, 14.2], [0.0, F, 12.7], [0.0, 0.0, 1.0]])
    # a thick, strongly refracting port close to the scene, so its bending moves silhouettes by many pixels
    model = CameraModel(K=K, width=W, height=H, distortion=np.zeros(5), kind="flat", thickness_m=0.05,
                        glass_index=1.77, water_index=1.34, distance_m=0.03)
    s = model.slab()
    scene = pt.PTScene(
        meshes=(pt_mesh(terrain, 0, 0.5), pt_mesh(spheres[0], 1, 0.7), pt_mesh(spheres[1], 2, 0.3)), K=K, width=W,
        height=H, world_from_cam=world_from_cam([0.3, -1.6, 1.9], [0.0, 0.0, 0.3], [0.0, 0.0, 1.0]),
        sigma_a=np.zeros(3), sigma_s=np.zeros(3), g=0.9, surface_z=5.0, sun_dir_world=np.array([0.0, 0.0, 1.0]),
        sun_irradiance_rgb=np.ones(3), sky_radiance_rgb=np.ones(3),
        slab=np.array([s.inner_m, s.outer_m, s.air_index, s.glass_index, s.water_index]))
    ids = pt.render_ids(scene)

    both = trimesh.util.concatenate([terrain, *spheres])
    face_ids = np.repeat([0, 1, 2], [len(terrain.faces), len(spheres[0].faces), len(spheres[1].faces)])
    T = scene.world_from_cam

    def cast(du: float, dv: float, port: bool = True) -> np.ndarray:
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        o, d = model.pixel_rays(u + du, v + dv) if port else (np.zeros((H, W, 3)), model.air_directions(u, v))
        origins, dirs = o.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3], d.reshape(-1, 3) @ T[:3, :3].T
        tri = both.ray.intersects_first(origins, dirs)
        return np.where(tri >= 0, face_ids[np.maximum(tri, 0)], 0).reshape(H, W)

    centre = ids_agree_off_silhouettes(ids, cast)
    assert (cast(0.0, 0.0, port=False) != centre).sum() >= 20  # without the port's bending many pixels differ


def ids_agree_off_silhouettes(ids: np.ndarray, cast) -> np.ndarray:
    """Asserts `ids` equal the ray cast at pixel centres wherever casts 1e-3 px off centre agree (at most two pixels
    sit that close to a silhouette); returns the centre cast."""
    centre = cast(0.0, 0.0)
    jittered = [cast(du, dv) for du, dv in [(1e-3, 0), (-1e-3, 0), (0, 1e-3), (0, -1e-3)]]
    ambiguous = np.any([j != centre for j in jittered], axis=0)
    assert ambiguous.sum() <= 2
    assert np.array_equal(ids[~ambiguous], centre[~ambiguous])
    return centre
