"""Tests of the physical light model on the GL path: the resolve shader's water against its float64 twin
(`seasynth.worker.light.volume`) on the samples it read, sun and lamp shadow maps, and which passes a frame's terms draw."""

import math

import numpy as np
import pytest
import trimesh
from test_render import draw, pinhole

from seasynth.worker.frame.srgb import encode_srgb8
from seasynth.worker.light import Lamp, Medium, PhysicalLight, Terms
from seasynth.worker.light.lamps import LAMP_Z_SPREAD
from seasynth.worker.light.sun import sun_in_water
from seasynth.worker.light.volume import volume
from seasynth.worker.render import Passes, Sampling, View
from seasynth.worker.scene.poses import look_at_pose, rigid_inverse

ONE = Sampling(msaa=1, supersample=1)
W, H = 48, 36


def camera(eye, target, hfov_deg: float, far: float = 200.0) -> tuple[View, np.ndarray]:
    """(view, world_from_cam) of a W x H pinhole at eye looking at target, world z up."""
    world_from_cam = look_at_pose(np.asarray(eye, float), np.asarray(target, float))
    view = View(K=pinhole(W, H, hfov_deg), width=W, height=H, cam_from_world=rigid_inverse(world_from_cam),
                near=0.05, far=far)
    return view, world_from_cam


def painted(mesh: trimesh.Trimesh, rgb) -> trimesh.Trimesh:
    mesh.visual.vertex_colors = np.tile([*rgb, 255], (len(mesh.vertices), 1))
    return mesh


def quad(corners, rgb=(180, 160, 120)) -> trimesh.Trimesh:
    return painted(trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False), rgb)


def sphere(key: str, centre, radius: float, rgb=(200, 80, 60)):
    pose = np.eye(4)
    pose[:3, 3] = centre
    return draw(key, painted(trimesh.creation.icosphere(subdivisions=3, radius=radius), rgb), 1, pose)


def lamp(position, direction, beam_deg=20.0, cutoff_deg=35.0, intensity=(3.0, 2.5, 2.0)) -> Lamp:
    d, cut = np.asarray(direction, float) / np.linalg.norm(direction), math.radians(cutoff_deg)
    return Lamp(position_cam=np.asarray(position, float), direction_cam=d, cutoff_rad=cut,
                beam_rad=math.radians(beam_deg), intensity=np.array(intensity, float))


def light(a, b, *, lamps=(), sun=True, sun_shadows=True, sky=True, surface_z=8.0, e0=None, sun_dir=None, esky=0.3,
          scattering=None, lamp_spread=True) -> PhysicalLight:
    if sun_dir is None:
        sun_dir, e = sun_in_water(np.array([0.3, 0.4, 0.866]) / np.linalg.norm([0.3, 0.4, 0.866]), 1.2)
        e0 = e if e0 is None else e0
    b = np.broadcast_to(np.asarray(b, float), (3,))
    terms = Terms(sun=sun, sun_shadows=sun_shadows, sky=sky, scattering=bool(b.max() > 0) if scattering is None
                  else scattering, lamps=len(lamps), lamp_spread=bool(lamps) and lamp_spread)
    return PhysicalLight(medium=Medium(a=np.broadcast_to(np.asarray(a, float), (3,)), b=b, g=0.9, surface_z=surface_z),
                         sun_dir_world=np.asarray(sun_dir, float), sun_irradiance=np.broadcast_to(e0, (3,)),
                         sky_irradiance=np.full(3, esky), lamps=tuple(lamps), terms=terms)


def pixel_rays(view: View, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dirs_world, dirs_cam), each (H, W, 3) float64 unit: K^-1 [u, v, 1] through the pixel centres."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(view.K).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d @ world_from_cam[:3, :3].T, d


def hit_points(view, world_from_cam, range_m) -> np.ndarray:
    """(H, W, 3) world points where the pixel-centre rays end (inf where they hit nothing)."""
    dirs_world, _ = pixel_rays(view, world_from_cam)
    with np.errstate(invalid="ignore"):
        return world_from_cam[:3, 3] + dirs_world * range_m[..., None]


# --- the resolve shader against its float64 twin ---------------------------------------------------------------

SEABED = quad([[-8, -3, 0], [8, -3, 0], [8, 20, 0], [-8, 20, 0]])
VIEW, WORLD_FROM_CAM = camera([0.0, -1.0, 1.6], [0.0, 5.0, 0.2], 70.0)  # its top rows look 15 degrees up: open water
SPHERE_CENTRE = np.array([0.3, 4.0, 0.9])
SCENE = [draw("test/render-light/seabed", SEABED, 0), sphere("test/render-light/sphere", SPHERE_CENTRE, 0.6)]
INSIDE_SPHERE = (rigid_inverse(WORLD_FROM_CAM) @ [*SPHERE_CENTRE, 1.0])[:3]
CLEAR, SCATTERING = [0.3, 0.07, 0.04], [0.1, 0.2, 0.3]
CASES = {
    "sun-sky-scattering": light(CLEAR, SCATTERING),
    # red: a = b = 1e5 / m, an optical depth of 1.4e6 down from the surface; green and blue moderate and clear
    "optical-depth-1e6": light([1e5, 0.3, 0.01], [1e5, 0.5, 0.02]),
    "zero-scattering": light(CLEAR, 0.0),
}
LAMP_CASES = {
    "sun-sky-scattering-lamp": light(CLEAR, SCATTERING, lamps=(lamp((0.3, 0.1, 0.0), (-0.05, 0.1, 1.0)),)),
    "optical-depth-1e6-lamp": light([1e5, 0.3, 0.01], [1e5, 0.5, 0.02], lamps=(lamp((0.3, 0.1, 0.0), (0, 0, 1)),)),
    "lamp-inside-sphere": light(CLEAR, SCATTERING, lamps=(lamp(INSIDE_SPHERE, (0.0, 0.0, 1.0)),)),
    "lamp-at-camera": light(CLEAR, SCATTERING, lamps=(lamp((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),)),
    # the term switched off (the fidelity bench's -lamp_spread row): forward-scattered light in the sharp profile
    "lamp-without-spread": light(CLEAR, SCATTERING, lamps=(lamp((0.3, 0.1, 0.0), (-0.05, 0.1, 1.0)),),
                                 lamp_spread=False),
}


def frame_and_twin(renderer, lt, view=VIEW, world_from_cam=WORLD_FROM_CAM, items=SCENE):
    """(the rendered image, float64 `volume` on the J and range of the very samples it resolved, that range)."""
    J, R = renderer.samples(view, items, lt, ONE)
    dirs_world, dirs_cam = pixel_rays(view, world_from_cam)
    depth = lt.medium.surface_z - world_from_cam[2, 3]
    expected = volume(J[0].astype(np.float64), R[0], dirs_world, dirs_cam, depth, lt)
    return renderer.render(view, items, lt, None, ONE, Passes()).image, expected, R[0]


@pytest.mark.parametrize("name", [*CASES, *LAMP_CASES])
def test_the_resolve_shader_is_its_float64_twin_to_one_code(renderer, name):
    lt = {**CASES, **LAMP_CASES}[name]
    image, expected, R = frame_and_twin(renderer, lt)
    assert np.all(np.isfinite(image)) and np.all(np.isfinite(expected))
    got8, want8 = encode_srgb8(image).astype(int), encode_srgb8(expected).astype(int)
    assert np.abs(got8 - want8).max() <= 1
    open_water, seen = ~np.isfinite(R), np.isfinite(R)
    assert open_water.sum() > 100 and seen.sum() > 1000  # both kinds of sample are in the frame
    if name.startswith("optical-depth"):
        # red is gone; blue shows the scene (its darkest samples, in the sun's shadow, get the sky alone)
        assert np.all(got8[..., 0] == 0) and np.all(got8[seen, 2] > 10)
    elif name == "zero-scattering":
        assert np.all(image[open_water] == 0.0)  # nothing scattered and no sky in view: open water is black
        assert np.all(got8[seen] > 0)
    else:
        assert np.all(got8[open_water, 1:] > 20)  # the in-scattered sun and sky light the open water


def test_a_frame_with_no_light_at_all_is_black(renderer):
    """Sun down and no lamps: the surface shader has nothing to shade (its normals compile out) and the water has
    nothing to scatter, so every sample is exactly black, with or without scattering water."""
    for b in (0.0, SCATTERING):
        lt = light(CLEAR, b, sun=False, sun_shadows=False, sky=False, e0=np.zeros(3))
        image = renderer.render(VIEW, SCENE, lt, None, ONE, Passes()).image
        assert image.shape == (H, W, 3) and np.all(image == 0.0)


def test_per_sample_shading_moves_where_a_lamp_is_shaded_not_how_much_light_arrives(renderer):
    """Rough terrain under a lamp beside the camera. Shading each of 4 samples at its own position instead of once at
    the pixel centre must leave the frame's mean lamp light as it was (within 1%): a sample shaded off the point where
    the shadow map sampled its triangle must not shadow itself. (Before the lookups moved off the surface along the
    normal, per-sample shading darkened such a frame by about 30%.)"""
    from seasynth.worker.scene.assets.terrain import heightfield

    terrain = heightfield(np.random.default_rng(3), "rock", 12.0, 96, 1.2)
    items = [draw("test/render-light/rock", terrain.mesh, 0)]
    view, _ = camera([0.0, -4.0, 2.0], [0.0, 1.0, 0.2], 60.0)
    lt = light(CLEAR, 0.0, sun=False, sun_shadows=False, sky=False, e0=np.zeros(3),
               lamps=(lamp((-0.35, 0.1, 0.0), (0.15, 0.35, 1.0), beam_deg=20.0, cutoff_deg=40.0),))
    means = []
    for per_sample in (False, True):
        J, R = renderer.samples(view, items, lt, Sampling(msaa=4, supersample=1, per_sample_shading=per_sample))
        assert np.isfinite(R).mean() > 0.7
        means.append(J[np.isfinite(R)].mean(axis=0))
    np.testing.assert_allclose(means[1], means[0], rtol=0.01)


def test_a_lamp_inside_the_sphere_lights_no_surface(renderer):
    """Its shadow map sees the sphere's inside all round, and the sphere's outside faces away from it: every sample's
    J is bit for bit the frame's without the lamp."""
    J_inside, R_inside = renderer.samples(VIEW, SCENE, LAMP_CASES["lamp-inside-sphere"], ONE)
    J_none, R_none = renderer.samples(VIEW, SCENE, light(CLEAR, SCATTERING), ONE)
    np.testing.assert_array_equal(J_inside, J_none)
    np.testing.assert_array_equal(R_inside, R_none)
    # while the same lamp at the camera (same axis) lights most of what the frame sees, and darkens nothing
    J_out, _ = renderer.samples(VIEW, SCENE, LAMP_CASES["lamp-at-camera"], ONE)
    assert np.sum(J_out[..., 1] > J_none[..., 1] + 0.01) > 300 and np.all(J_out >= J_none)


def test_a_lamp_pointing_away_from_the_scene_adds_exactly_nothing(renderer):
    """Behind the camera and facing back: no view ray and no surface is in its cone."""
    away = light(CLEAR, SCATTERING, lamps=(lamp((0.3, 0.0, 0.0), (0.0, 0.0, -1.0), cutoff_deg=60.0),))
    image, expected, _ = frame_and_twin(renderer, away)
    without = renderer.render(VIEW, SCENE, light(CLEAR, SCATTERING), None, ONE, Passes()).image
    np.testing.assert_array_equal(image, without)
    np.testing.assert_array_equal(expected, frame_and_twin(renderer, light(CLEAR, SCATTERING))[1])


# --- shadows ---------------------------------------------------------------------------------------------------

FLOOR = draw("test/render-light/floor", quad([[-8, -8, 0], [8, -8, 0], [8, 8, 0], [-8, 8, 0]], (200, 200, 200)), 0)
BALL = sphere("test/render-light/ball", [0.0, 0.0, 1.0], 0.5, (200, 200, 200))
SHADOW_VIEW, SHADOW_WORLD_FROM_CAM = camera([0.0, -4.0, 3.0], [0.0, 0.0, 0.3], 60.0, far=100.0)


def overhead_sun(a, b, shadows: bool) -> PhysicalLight:
    """The sun straight above (E0 = 0.9), no sky, no in-scattering: the image is J exp(-K range)."""
    return light(a, b, sun_shadows=shadows, sky=False, scattering=False, surface_z=6.0, e0=np.full(3, 0.9),
                 sun_dir=[0.0, 0.0, 1.0])


def floor_pixels(renderer, lt):
    """(image, range, floor points' distance from below the ball's centre (inf off the floor))."""
    res = renderer.render(SHADOW_VIEW, [FLOOR, BALL], lt, None, ONE, Passes(ids=True, range=True))
    p = hit_points(SHADOW_VIEW, SHADOW_WORLD_FROM_CAM, res.range_m.astype(np.float64))
    on_floor = (res.instance == 0) & np.isfinite(res.range_m)
    return res.image, res.range_m.astype(np.float64), np.where(on_floor, np.hypot(p[..., 0], p[..., 1]), np.inf)


@pytest.mark.parametrize("b", [0.0, 0.15])
def test_the_floor_below_a_ball_loses_the_sun_and_only_there(renderer, b):
    """Sun straight above, no sky, no in-scattering. Under the ball (0.1 m inside the umbra's 0.5 m edge, past the
    forward-scattered part's 0.05 m blur) the floor is black: both parts of the sun are shadowed, the unscattered
    exactly, the forward-scattered one (0 anyway when b = 0) by the coarse map's filtered tap. Away from the ball, and everywhere
    with sun_shadows off, it is lit: albedo E0 exp(-K D) exp(-K range), to J's half-float storage (2^-10)."""
    a = np.array([1e-3, 2e-3, 4e-3])
    albedo = FLOOR.mesh.albedo[0].astype(np.float64)
    K = overhead_sun(a, b, shadows=True).medium.k
    image, R, r = floor_pixels(renderer, overhead_sun(a, b, shadows=True))
    open_image, _, _ = floor_pixels(renderer, overhead_sun(a, b, shadows=False))
    under, away = r < 0.4, (r > 1.0) & np.isfinite(r)
    assert under.sum() >= 12 and away.sum() > 800
    lit = albedo * 0.9 * np.exp(-K * 6.0) * np.exp(-K * R[..., None])
    np.testing.assert_allclose(open_image[under], lit[under], rtol=1.1e-3, atol=0)
    np.testing.assert_allclose(image[away], lit[away], rtol=1.1e-3, atol=0)
    np.testing.assert_array_equal(image[away], open_image[away])
    assert np.all(image[under] == 0.0) and np.all(open_image[under] > 0.4)


WALL = draw("test/render-light/wall", quad([[-8, 6, -2], [8, 6, -2], [8, 6, 6], [-8, 6, 6]], (200, 200, 200)), 0)
BLOCKER_CENTRE = np.array([0.0, 2.0, 2.0])
BLOCKER = sphere("test/render-light/blocker", BLOCKER_CENTRE, 0.4, (200, 200, 200))
WALL_VIEW, WALL_WORLD_FROM_CAM = camera([0.0, 0.0, 2.0], [0.0, 10.0, 2.0], 90.0, far=100.0)
SIDE_LAMP = lamp((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), beam_deg=40.0, cutoff_deg=60.0, intensity=(2.0, 2.0, 2.0))


def test_a_lamps_light_does_not_reach_the_wall_behind_a_ball(renderer):
    """A lamp 1 m right of the camera: the ball 2 m ahead shades the wall 6 m ahead to the left of the ball's image.
    There the frame equals the frame without the lamp (the sky lights both), to 1 code; in the lamp's beam off the
    shadow it is brighter."""

    def frame(lamps):
        lt = light(0.01, 0.0, lamps=lamps, sun=False, sun_shadows=False, surface_z=10.0)
        return renderer.render(WALL_VIEW, [WALL, BLOCKER], lt, None, ONE, Passes(ids=True, range=True))

    on, off = frame((SIDE_LAMP,)), frame(())
    p = hit_points(WALL_VIEW, WALL_WORLD_FROM_CAM, on.range_m.astype(np.float64))
    lamp_world = WALL_WORLD_FROM_CAM[:3, :3] @ SIDE_LAMP.position_cam + WALL_WORLD_FROM_CAM[:3, 3]
    on_wall = (on.instance == 0) & np.isfinite(on.range_m)
    ray = np.where(on_wall[..., None], p - lamp_world, 1.0)
    # distance from the ball's centre to the segment lamp -> wall point, and the point's angle off the lamp's axis
    s = np.clip(((BLOCKER_CENTRE - lamp_world) * ray).sum(-1) / (ray * ray).sum(-1), 0.0, 1.0)
    miss = np.linalg.norm(lamp_world + s[..., None] * ray - BLOCKER_CENTRE, axis=-1)
    axis_world = WALL_WORLD_FROM_CAM[:3, :3] @ SIDE_LAMP.direction_cam
    off_axis = np.degrees(np.arccos((ray @ axis_world) / np.linalg.norm(ray, axis=-1)))
    shadow = on_wall & (miss < 0.35)
    beam = on_wall & (miss > 0.5) & (off_axis < 40.0)
    assert shadow.sum() >= 40 and beam.sum() > 500
    got, without = encode_srgb8(on.image).astype(int), encode_srgb8(off.image).astype(int)
    assert np.abs(got - without)[shadow].max() <= 1
    assert np.all((got - without)[beam] >= 3)


# --- only the passes a frame needs -----------------------------------------------------------------------------

DRAW_AND_READ = ("surface+range", "resolve+water", "read image")


@pytest.mark.parametrize(("terms", "before"), [
    (dict(sun=False, sun_shadows=False, sky=True), ()),
    (dict(sun=True, sun_shadows=False, sky=True), ()),
    (dict(sun=False, sun_shadows=True, sky=True), ()),  # no sun: no map for it
    (dict(sun=True, sun_shadows=True, sky=False), ("sun shadow",)),
], ids=["sky-only", "sun-unshadowed", "shadows-without-sun", "sun-shadows"])
def test_a_frame_draws_a_shadow_map_only_for_a_shadowed_sun(renderer, terms, before):
    lt = light(CLEAR, 0.0, **terms)
    assert renderer.render(VIEW, SCENE, lt, None, ONE, Passes()).passes == (*before, *DRAW_AND_READ)


def test_a_frame_draws_one_shadow_map_per_lamp_after_the_suns(renderer):
    lamps = (lamp((0.3, 0.0, 0.0), (0, 0, 1)), lamp((-0.3, 0.0, 0.0), (0, 0, 1)))
    only_lamps = light(CLEAR, 0.0, lamps=lamps, sun=False, sun_shadows=False, sky=False)
    assert renderer.render(VIEW, SCENE, only_lamps, None, ONE, Passes()).passes == (
        "lamp0 shadow", "lamp1 shadow", *DRAW_AND_READ)
    everything = light(CLEAR, SCATTERING, lamps=lamps[:1])
    assert renderer.render(VIEW, SCENE, everything, None, ONE, Passes()).passes == (
        "sun shadow", "lamp0 shadow", *DRAW_AND_READ)


FOUR = Sampling(msaa=4, supersample=1)


@pytest.mark.parametrize("name", list(LAMP_CASES))
def test_with_four_samples_a_pixel_the_resolve_is_its_twin_and_lamp_scattering_once_a_pixel_costs_no_accuracy(
        renderer, name):
    """volume_pixels (the lamps' scattering once a pixel where the samples' ray ends agree within LAMP_Z_SPREAD) is
    the shader to one code; against every sample integrated on its own it differs by under 1e-5 (linear; 2.7e-6
    measured), on frames where a third of the pixels take the once-a-pixel path with their samples' ends apart."""
    from seasynth.worker.light.volume import volume_pixels

    lt = LAMP_CASES[name]
    J, R = renderer.samples(VIEW, SCENE, lt, FOUR)
    dirs_world, dirs_cam = pixel_rays(VIEW, WORLD_FROM_CAM)
    depth = lt.medium.surface_z - WORLD_FROM_CAM[2, 3]
    twin = volume_pixels(J, R, dirs_world, dirs_cam, depth, lt)
    image = renderer.render(VIEW, SCENE, lt, None, FOUR, Passes()).image
    assert np.abs(encode_srgb8(image).astype(int) - encode_srgb8(twin).astype(int)).max() <= 1
    per_sample = np.mean([volume(Jk.astype(np.float64), Rk, dirs_world, dirs_cam, depth, lt)
                          for Jk, Rk in zip(J, R)], axis=0)
    assert np.abs(twin - per_sample).max() < 1e-5
    lo, hi = R.min(axis=0), R.max(axis=0)  # the scene's surfaces lie below the water surface: ends are ranges
    with np.errstate(invalid="ignore"):  # open water: inf - inf
        assert ((hi > lo) & (hi - lo <= LAMP_Z_SPREAD * lo)).mean() > 0.3
