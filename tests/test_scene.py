"""Tests of seasynth.worker.scene.sample: objects resting on the terrain in their workspaces, the camera, the look-at point and
where every draw comes from. Sampling needs no GL: a RenderSession that is never entered serves the assets."""

import math
import random

import numpy as np
import pytest
from scipy import stats

from seasynth.service.seeds import frame_rng
from seasynth.service.spec.dataset import load_spec
from seasynth.service.spec.scene import Box
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.scene.placement import footprint_radius, in_box
from seasynth.worker.scene.poses import rotation_between
from seasynth.worker.scene.sample import CAMERA_CLEARANCE_M, Scene, sample_scene

EXAMPLE = "examples/urchins.yaml"
FRAMES = range(40)
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def session():
    return RenderSession()  # not entered: no GL context, only the asset and terrain sources


@pytest.fixture(scope="module")
def spec():
    return load_spec(EXAMPLE)


@pytest.fixture(scope="module")
def scenes(session, spec):
    return [session.scene(spec, i) for i in FRAMES]


def record(scene: Scene) -> list:
    """Every sampled value of a scene, flattened to (name, array) pairs for exact comparison."""
    out = [("terrain", np.array(scene.terrain.key)), ("terrain_albedo", np.r_[scene.terrain_albedo_scale,
                                                                             scene.terrain_albedo_bias])]
    for p in scene.objects:
        out += [(f"object {p.instance_id}", np.array([p.instance_id, p.role, p.class_name, p.asset.key, p.variant],
                                                    dtype=object)),
                (f"pose {p.instance_id}", p.world_from_obj), (f"scale {p.instance_id}", np.array(p.scale)),
                (f"albedo {p.instance_id}", np.r_[p.albedo_scale, p.albedo_bias]),
                (f"footprint {p.instance_id}", np.array(p.footprint_m))]
    w = scene.water
    out += [("camera", scene.world_from_cam), ("look_at", scene.look_at),
            ("look_at_instance", np.array(scene.look_at_instance, dtype=object)),
            ("camera_tries", np.array(scene.camera_tries)), ("dropped", np.array(scene.dropped)),
            ("light", np.r_[scene.lighting.sun_dir_world, scene.lighting.sun_intensity, scene.lighting.ambient]),
            ("water", np.array(None, dtype=object) if w is None else np.r_[w.beta_D, w.beta_B, w.B_inf]),
            ("water_type", np.array(scene.water_type, dtype=object))]
    return out


def assert_same_scene(a: Scene, b: Scene) -> None:
    ra, rb = record(a), record(b)
    assert [n for n, _ in ra] == [n for n, _ in rb]
    for (name, x), (_, y) in zip(ra, rb):
        assert x.shape == y.shape and np.array_equal(x, y), name


def anchor_vertex(scene: Scene, anchor: np.ndarray) -> int:
    """The index of the terrain vertex the anchor sits on (exactly)."""
    v = np.asarray(scene.terrain.mesh.vertices)
    i = int(np.argmin(np.linalg.norm(v - anchor, axis=1)))
    np.testing.assert_array_equal(v[i], anchor)
    return i


def angle_weighted_normal(mesh, vertex: int) -> np.ndarray:
    """The unit normal at a vertex: its faces' normals weighted by their angles there (trimesh's definition)."""
    faces = np.asarray(mesh.faces)
    v = np.asarray(mesh.vertices)
    rows, cols = np.nonzero(faces == vertex)
    tri = v[faces[rows]]  # (k, 3, 3)
    here = tri[np.arange(len(rows)), cols]
    a = tri[np.arange(len(rows)), (cols + 1) % 3] - here
    b = tri[np.arange(len(rows)), (cols + 2) % 3] - here
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    total = (n * np.arccos(np.clip(cos, -1, 1))[:, None]).sum(axis=0)
    return total / np.linalg.norm(total)


def yaw_of(p) -> float:
    """The yaw about the object's own up axis, once the tilt onto the terrain normal is taken out."""
    R = p.world_from_obj[:3, :3] / p.scale
    Rz = rotation_between(UP, R[:, 2]).T @ R
    np.testing.assert_allclose(Rz[2], UP, atol=1e-12)  # a pure rotation about z
    return math.atan2(Rz[1, 0], Rz[0, 0]) % (2 * math.pi)


# --- rotation_between -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("b", [[0, 0, 1.0], [0.3, -0.2, 0.9], [1.0, 0, 0], [0.01, 0, -1.0], [0, 0, -1.0]])
def test_rotation_between_is_the_shortest_arc(b):
    a = UP
    b = np.asarray(b) / np.linalg.norm(b)
    R = rotation_between(a, b)
    # 1e-9: near-opposite vectors lose digits in the 1 / (1 + cos) term (1e-11 at 179.4 degrees).
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(R @ a, b, atol=1e-9)
    # Shortest arc: its angle is the angle between a and b (trace = 1 + 2 cos angle).
    assert (np.trace(R) - 1) / 2 == pytest.approx(float(a @ b), abs=1e-9)


# --- objects ----------------------------------------------------------------------------------------------------


def test_ids_roles_counts_scales_and_albedo(spec, scenes):
    for scene in scenes:
        objs = scene.objects
        assert [p.instance_id for p in objs] == list(range(1, len(objs) + 1))
        roles = [p.role for p in objs]
        n_t = roles.count("target")
        assert roles == ["target"] * n_t + ["distractor"] * (len(objs) - n_t)  # targets first
        (targets,) = spec.targets
        assert n_t <= targets.count[1] and len(objs) - n_t <= spec.distractors.count[1]
        lo = targets.count[0] + spec.distractors.count[0]
        hi = targets.count[1] + spec.distractors.count[1]
        assert lo <= len(objs) + scene.dropped <= hi
        for p in objs:
            group = targets if p.role == "target" else spec.distractors
            assert p.class_name == (targets.class_name if p.role == "target" else None)
            kinds = {a.procedural for a in group.assets}
            kind, variant = p.asset.key.split("/")[1:3]
            assert kind in kinds and int(variant) == p.variant
            assert group.scale[0] <= p.scale <= group.scale[1]
            assert np.all((p.albedo_scale >= spec.texture.scale[0]) & (p.albedo_scale <= spec.texture.scale[1]))
            assert np.all((p.albedo_bias >= spec.texture.bias[0]) & (p.albedo_bias <= spec.texture.bias[1]))


def test_every_anchor_lies_in_its_roles_workspace(spec, scenes):
    ws = spec.workspaces
    for scene in scenes:
        for p in scene.objects:
            box = ws.targets if p.role == "target" else ws.distractors
            assert in_box(p.world_from_obj[None, :3, 3], box)[0], (p.role, p.world_from_obj[:3, 3])
    # The distractors' workspace is wider: some distractors use it outside the targets' box.
    outside = [p for s in scenes for p in s.objects if p.role == "distractor"
               and not in_box(p.world_from_obj[None, :3, 3], ws.targets)[0]]
    assert len(outside) >= 20


def test_objects_rest_on_the_terrain_aligned_to_its_normal(scenes):
    for scene in scenes:
        for p in scene.objects:
            anchor = p.world_from_obj[:3, 3]
            vertex = anchor_vertex(scene, anchor)  # on a terrain vertex, so on the surface
            assert anchor[2] == pytest.approx(scene.terrain.height_at(anchor[None, :2])[0], abs=1e-9)
            np.testing.assert_array_equal(p.world_from_obj[3], [0, 0, 0, 1])
            R = p.world_from_obj[:3, :3] / p.scale
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)  # rotation times the object's scale
            assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
            np.testing.assert_allclose(R[:, 2], angle_weighted_normal(scene.terrain.mesh, vertex), atol=1e-9)


def test_yaw_is_uniform(scenes):
    yaws = np.array([yaw_of(p) for s in scenes for p in s.objects])
    assert len(yaws) >= 400
    assert stats.kstest(yaws / (2 * math.pi), "uniform").pvalue > 0.01
    assert np.all(np.histogram(yaws, bins=8, range=(0, 2 * math.pi))[0] >= len(yaws) / 16)


def world_vertices(p) -> np.ndarray:
    """(n, 3) float64: the object's vertices in the world, metres."""
    v = np.asarray(p.asset.mesh.vertices, dtype=np.float64)
    return v @ p.world_from_obj[:3, :3].T + p.world_from_obj[:3, 3]


def test_footprint_radius_is_the_reach_of_the_transformed_vertices():
    stick = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.1, 0.0, 0.0]])
    assert footprint_radius(stick, 3.0 * np.eye(3)) == pytest.approx(0.3, abs=1e-15)
    theta = 0.4  # tilted about x: the top of the stick leans out by 2 sin(theta)
    tilt = np.array([[1.0, 0, 0], [0, math.cos(theta), -math.sin(theta)], [0, math.sin(theta), math.cos(theta)]])
    assert footprint_radius(stick, tilt) == pytest.approx(2 * math.sin(theta), abs=1e-15)


def test_placed_objects_do_not_interpenetrate(session, spec, scenes):
    pairs = tilted_reach = 0
    for i in range(200):
        scene = scenes[i] if i < len(scenes) else session.scene(spec, i)
        objs = scene.objects
        world = [world_vertices(p) for p in objs]
        anchors = np.array([p.world_from_obj[:2, 3] for p in objs])
        reach = np.array([np.linalg.norm(w[:, :2] - a, axis=1).max() for w, a in zip(world, anchors)])
        np.testing.assert_allclose([p.footprint_m for p in objs], reach, rtol=1e-12, atol=0)
        upright = np.array([p.scale * np.linalg.norm(np.asarray(p.asset.mesh.vertices)[:, :2], axis=1).max()
                            for p in objs])
        tilted_reach = max(tilted_reach, float((reach / upright).max()))
        for a in range(len(objs)):
            for b in range(a + 1, len(objs)):
                gap = anchors[b] - anchors[a]
                assert np.linalg.norm(gap) >= reach[a] + reach[b], (i, a + 1, b + 1)
                # A separating vertical plane, checked on the vertices themselves: no interpenetration.
                u = gap / np.linalg.norm(gap)
                assert (world[a][:, :2] @ u).max() <= (world[b][:, :2] @ u).min(), (i, a + 1, b + 1)
                pairs += 1
    assert pairs >= 10_000
    assert tilted_reach > 1.5  # tilted objects reach well past their upright footprint: the tilt is counted


def test_an_object_with_no_free_spot_is_left_out(session, spec):
    one_vertex = Box(min=(-0.01, -0.01, -2.0), max=(0.01, 0.01, 2.0))  # the terrain vertex at (0, 0)
    s = spec.model_copy(update={
        "targets": [spec.targets[0].model_copy(update={"count": (3, 3)})],
        "distractors": spec.distractors.model_copy(update={"count": (0, 0)}),
        "workspaces": spec.workspaces.model_copy(update={"targets": one_vertex}),
    })
    for i in range(3):
        scene = session.scene(s, i)
        [target] = scene.objects
        np.testing.assert_array_equal(target.world_from_obj[:2, 3], [0.0, 0.0])
        assert scene.dropped == 2  # after PLACEMENT_TRIES draws each


# --- camera and look-at point -----------------------------------------------------------------------------------


def test_camera_lies_in_its_workspace_clear_of_geometry_and_looks_at_the_look_at_point(spec, scenes):
    near = spec.camera.clip[0]
    for scene in scenes:
        T = scene.world_from_cam
        eye = T[:3, 3]
        assert in_box(eye[None], spec.workspaces.camera)[0]
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        forward = (scene.look_at - eye) / np.linalg.norm(scene.look_at - eye)
        np.testing.assert_allclose(T[:3, 2], forward, atol=1e-12)  # KITTI z forward
        assert T[2, 0] == pytest.approx(0.0, abs=1e-12)  # image rows stay level
        assert T[2, 1] < 0  # image y (down) points down in the world
        assert eye[2] >= scene.terrain.height_at(eye[None, :2])[0] + CAMERA_CLEARANCE_M + near
    # Uniform in the workspace: nothing in the example's camera box is near geometry, so no draw is refused.
    assert all(s.camera_tries == 1 for s in scenes)
    box = spec.workspaces.camera
    unit = (np.array([s.world_from_cam[:3, 3] for s in scenes]) - box.min) / np.subtract(box.max, box.min)
    assert all(stats.kstest(unit[:, axis], "uniform").pvalue > 0.01 for axis in range(3))


def with_jitter(spec, sigma: float):
    return spec.model_copy(update={"camera": spec.camera.model_copy(update={"look_at_jitter_m": sigma})})


def test_look_at_is_a_target_in_the_look_at_workspace_plus_gaussian_jitter(session, spec, scenes):
    exact = [session.scene(with_jitter(spec, 0.0), i) for i in FRAMES]
    wide = [session.scene(with_jitter(spec, 0.5), i) for i in FRAMES]
    sigma = spec.camera.look_at_jitter_m
    offsets, ranks = [], set()
    for scene, ex, wi in zip(scenes, exact, wide):
        eligible = [p for p in scene.objects
                    if p.role == "target" and in_box(p.world_from_obj[None, :3, 3], spec.workspaces.look_at)[0]]
        if not eligible:  # falls back to the seabed (next test); 1 of the 40 frames
            assert scene.look_at_instance is None
            continue
        chosen = next(p for p in eligible if p.instance_id == scene.look_at_instance)
        ranks.add(eligible.index(chosen))
        # Without jitter the camera looks at the target's anchor exactly; the jitter moves nothing else.
        np.testing.assert_array_equal(ex.look_at, chosen.world_from_obj[:3, 3])
        for other in (ex, wi):
            assert other.look_at_instance == scene.look_at_instance
            np.testing.assert_array_equal(other.world_from_cam[:3, 3], scene.world_from_cam[:3, 3])
            assert [p.world_from_obj.tobytes() for p in other.objects] == [
                p.world_from_obj.tobytes() for p in scene.objects]
        # The jitter is sigma times one standard normal 3-vector of the frame, whatever sigma is.
        unit = (scene.look_at - ex.look_at) / sigma
        np.testing.assert_allclose((wi.look_at - ex.look_at) / 0.5, unit, rtol=1e-9, atol=1e-9)
        offsets.append(unit)
    assert len(offsets) >= 35
    offsets = np.concatenate(offsets)
    assert abs(offsets.mean()) < 0.35 and 0.75 < offsets.std() < 1.3
    assert len(ranks) >= 3  # the target is drawn, not always the first one


@pytest.mark.parametrize("case", ["no-targets", "targets-outside-look-at"])
def test_with_no_target_in_the_look_at_workspace_the_camera_looks_at_the_seabed(session, spec, case):
    look_at_box = Box(min=(-1.0, -1.0, -2.0), max=(1.0, 1.0, 0.16))
    update = {"camera": spec.camera.model_copy(update={"look_at_jitter_m": 0.0})}
    workspaces = {"look_at": look_at_box}
    if case == "no-targets":
        update["targets"] = [spec.targets[0].model_copy(update={"count": (0, 0)})]
    else:
        workspaces["targets"] = Box(min=(2.0, 2.0, -2.0), max=(3.0, 3.0, 2.0))
    update["workspaces"] = spec.workspaces.model_copy(update=workspaces)
    s = spec.model_copy(update=update)
    zs = []
    for i in range(10):
        scene = session.scene(s, i)
        assert scene.look_at_instance is None
        assert (case == "no-targets") == (not any(p.role == "target" for p in scene.objects))
        x, y, z = scene.look_at
        assert -1.0 <= x <= 1.0 and -1.0 <= y <= 1.0
        ground = scene.terrain.height_at(scene.look_at[None, :2])[0]
        assert z == pytest.approx(min(max(ground, -2.0), 0.16), abs=1e-12)
        zs.append(z)
    # On the seabed, held inside the workspace where the seabed is higher.
    assert min(zs) < 0.16 and max(zs) == 0.16


# --- where the draws come from ----------------------------------------------------------------------------------


def test_same_seed_and_index_give_the_same_scene_and_other_indices_or_seeds_another(session, spec, scenes):
    for i in (0, 7):
        assert_same_scene(session.scene(spec, i), scenes[i])
        assert_same_scene(sample_scene(spec, frame_rng(spec.seed, i), session.asset_for, session.terrain_for),
                          scenes[i])
    cams = {s.world_from_cam.tobytes() for s in scenes}
    poses = {s.objects[0].world_from_obj.tobytes() for s in scenes}
    assert len(cams) == len(poses) == len(scenes)
    other_seed = spec.model_copy(update={"seed": spec.seed + 1})
    for i in (0, 7):
        other = session.scene(other_seed, i)
        assert other.world_from_cam.tobytes() != scenes[i].world_from_cam.tobytes()
        assert other.objects[0].world_from_obj.tobytes() != scenes[i].objects[0].world_from_obj.tobytes()


def test_no_draw_comes_from_global_random_state(session, spec, scenes):
    for seed in (0, 12345):
        np.random.seed(seed)
        random.seed(seed)
        np_state, py_state = np.random.get_state(), random.getstate()
        scene = session.scene(spec, 3)
        assert_same_scene(scene, scenes[3])
        # Nothing read the global generators: their states did not move.
        assert random.getstate() == py_state
        after = np.random.get_state()
        assert all(np.array_equal(a, b) for a, b in zip(after, np_state))


def test_the_scene_is_a_function_of_the_generator_state_alone(session, spec, scenes):
    rng = frame_rng(spec.seed, 5)
    state = rng.bit_generator.state
    first = sample_scene(spec, rng, session.asset_for, session.terrain_for)
    rng.bit_generator.state = state
    assert_same_scene(sample_scene(spec, rng, session.asset_for, session.terrain_for), first)
    assert_same_scene(first, scenes[5])
