"""The seabed beyond the tile (worker.scene.far_field): its rings close the seam and cover the plane out to the
reach, and no rendered ray that points down ends in open water while the water would still let a seabed be seen."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seasynth.bench.horizon import VISIBLE, ray_directions
from seasynth.service.spec.dataset import load_spec
from seasynth.service.water import JERLOV_TYPES
from seasynth.worker.frame.function import PRESETS
from seasynth.worker.frame.srgb import decode_srgb8, encode_srgb8
from seasynth.worker.render import Passes
from seasynth.worker.scene.assets.terrain import STYLES, heightfield
from seasynth.worker.scene.far_field import (
    BLEND_M,
    FIRST_RING_M,
    RELIEF,
    RELIEF_WAVELENGTH_M,
    TONE,
    far_field,
    far_noise,
    far_seabed,
    ring_distances,
    seabed_of,
)
from seasynth.worker.scene.poses import look_at_pose, rigid_inverse

EXAMPLE = "examples/urchins.yaml"


def edges_of(faces: np.ndarray) -> tuple[set, set]:
    """(every undirected edge, the edges used by exactly one face) of a triangle list."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    keys, counts = np.unique(e, axis=0, return_counts=True)
    return {tuple(k) for k in keys}, {tuple(k) for k in keys[counts == 1]}


@settings(max_examples=12, deadline=None)
@given(style=st.sampled_from(STYLES), seed=st.integers(0, 2**31), size=st.floats(2.0, 60.0),
       cells=st.integers(2, 96), relief=st.floats(0.0, 3.0), reach=st.floats(1.0, 800.0))
def test_the_rings_close_the_seam_face_up_and_cover_the_plane_out_to_the_reach(style, seed, size, cells, relief,
                                                                                reach):
    terrain = heightfield(np.random.default_rng(seed), style, size, cells, relief)
    far = far_field(terrain, reach).mesh
    v, f = np.asarray(far.vertices), np.asarray(far.faces)
    n = cells + 1
    # The inner ring is the tile's boundary: the same points, and each of its edges is a boundary edge of the tile.
    tile_v = np.asarray(terrain.mesh.vertices)
    ring0 = 4 * cells
    grid_index = np.rint((v[:ring0, :2] - tile_v[0, :2]) / (size / cells)).astype(np.int64)
    np.testing.assert_array_equal(v[:ring0], tile_v[grid_index[:, 1] * n + grid_index[:, 0]])
    _, tile_boundary = edges_of(np.asarray(terrain.mesh.faces))
    _, far_boundary = edges_of(f)
    inner = {tuple(sorted((grid_index[i, 1] * n + grid_index[i, 0], grid_index[(i + 1) % ring0, 1] * n
                           + grid_index[(i + 1) % ring0, 0]))) for i in range(ring0)}
    assert inner == tile_boundary
    assert {tuple(sorted(e)) for e in far_boundary if max(e) < ring0} == {
        tuple(sorted((i, (i + 1) % ring0))) for i in range(ring0)}
    # Face up, no fold: every triangle's normal points up.
    assert (np.asarray(far.face_normals)[:, 2] > 0).all()
    # No overlap and no hole: the triangles' projected areas sum to the outer square less the tile.
    outer = size + 2 * ring_distances(reach)[-1]
    tri = v[f][:, :, :2]
    ab, ac = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    projected = 0.5 * np.abs(ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]).sum()
    assert projected == pytest.approx(outer**2 - size**2, rel=1e-9)
    assert ring_distances(reach)[-1] >= reach and ring_distances(reach)[0] == FIRST_RING_M
    assert np.isfinite(v).all()


def test_the_far_field_is_a_pure_function_of_the_terrain_and_the_reach():
    terrain = heightfield(np.random.default_rng(3), "pebbles", 12.0, 48, 0.25)
    a = far_field.__wrapped__(terrain, 300.0)
    b = far_field.__wrapped__(terrain, 300.0)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.visual.vertex_colors, b.mesh.visual.vertex_colors)
    assert a.key == b.key and a.key != far_field(terrain, 200.0).key


def open_water_where_a_seabed_shows(session, water: str, model: str, eye, yaw: float, pitch: float,
                                    far_field_on: bool = True, mesh_path=None) -> tuple[int, int]:
    """(rays that point down to a seabed the water lets be seen, of them those whose range is +inf), for a camera
    at `eye` looking along (yaw, pitch), in Jerlov water `water` under `model`."""
    spec = load_spec(EXAMPLE, {"camera.width": 64, "camera.height": 48, "camera.hfov_deg": 90.0,
                               "water.jerlov": [water], "water.model": model, "water.depth_m": [30.0, 30.0],
                               "terrain.far_field": far_field_on, "quality": "draft",
                               **({"terrain.mesh": {"path": str(mesh_path)}} if mesh_path else {})})
    scene = session.scene(spec, 0)
    look = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    world_from_cam = look_at_pose(np.asarray(eye, np.float64), np.asarray(eye, np.float64) + look)
    scene = dataclasses.replace(scene, world_from_cam=world_from_cam)
    view = dataclasses.replace(session.view(spec, scene), cam_from_world=rigid_inverse(world_from_cam))
    light = scene.light if scene.light is not None else scene.lighting
    result = session.renderer.render(view, session.draw_items(scene), light, scene.water, PRESETS["draft"],
                                     Passes(range=True))
    K = scene.light.medium.k if scene.light is not None else scene.water.beta_D
    floor = 0.0 if scene.far_field is None else min(0.0, float(np.asarray(scene.far_field.mesh.vertices)[:, 2].min()))
    w = ray_directions(view, world_from_cam)
    with np.errstate(divide="ignore"):
        t_floor = np.where(w[..., 2] < 0, (eye[2] - floor) / -w[..., 2], np.inf)  # where the ray is below the seabed
    seen = (t_floor < view.far) & (np.exp(-float(np.min(K)) * t_floor) > VISIBLE)
    return int(seen.sum()), int((seen & ~np.isfinite(result.range_m)).sum())


@settings(max_examples=24, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(water=st.sampled_from(JERLOV_TYPES), model=st.sampled_from(["physical", "paper"]),
       x=st.floats(-5.5, 5.5), y=st.floats(-5.5, 5.5), height=st.floats(0.5, 6.0),
       yaw=st.floats(0.0, 2 * math.pi), pitch=st.floats(math.radians(-50), math.radians(20)))
def test_no_ray_that_points_down_ends_in_open_water_while_the_water_would_show_a_seabed(
        render_session, water, model, x, y, height, yaw, pitch):
    seen, open_water = open_water_where_a_seabed_shows(render_session, water, model, (x, y, height), yaw, pitch)
    assert open_water == 0, (seen, open_water)


def test_without_the_far_field_the_tiles_edge_is_a_false_horizon(render_session):
    """The check above can fail: the tile alone, seen level from near its edge in clear water."""
    for on, expect_open in ((False, True), (True, False)):
        seen, open_water = open_water_where_a_seabed_shows(render_session, "I", "physical", (4.0, 0.0, 1.0), 0.0,
                                                           math.radians(-5), far_field_on=on)
        assert seen > 500 and (open_water > 0) == expect_open, (on, seen, open_water)


def test_a_user_terrain_mesh_is_continued_to_the_horizon_too(render_session, tmp_path):
    """A user's seabed mesh (here an 8 x 6 m heightfield file) gets the same rings, from its height grid's edge."""
    import trimesh

    from seasynth.worker.scene.assets.terrain import grid_faces

    nx, ny = 33, 25
    x, y = np.meshgrid(np.linspace(-4.0, 4.0, nx), np.linspace(-3.0, 3.0, ny))
    z = 0.3 + 0.2 * np.sin(x) * np.cos(1.3 * y)
    mesh = trimesh.Trimesh(np.column_stack([x.ravel(), y.ravel(), z.ravel()]), grid_faces(nx, ny), process=False)
    path = tmp_path / "seabed.obj"
    mesh.export(path)
    rng = np.random.default_rng(5)
    checked = 0
    for k in range(12):
        eye = (rng.uniform(-3.5, 3.5), rng.uniform(-2.5, 2.5), rng.uniform(1.0, 4.0))
        seen, open_water = open_water_where_a_seabed_shows(
            render_session, JERLOV_TYPES[k % len(JERLOV_TYPES)], "physical", eye, rng.uniform(0, 2 * math.pi),
            math.radians(rng.uniform(-35, 10)), mesh_path=path)
        assert open_water == 0, (k, seen, open_water)
        checked += seen
    assert checked > 5000


def test_the_committed_horizon_table_is_what_the_changelog_quotes():
    """bench/results/cpu/horizon: the example's 40 frames at 320x240, with false horizons only without the far field
    (the bench renders them; this reads what it wrote)."""
    import json
    from pathlib import Path

    result = json.loads((Path(__file__).resolve().parents[1] / "bench/results/cpu/horizon/horizon.json").read_text())
    assert result["spec"] == EXAMPLE and result["frames"] == 40 and result["size"] == [320, 240]
    assert result["rows"]["on"] == {"frames": 0, "pixels": 0, "pixel_share": 0.0}
    assert result["rows"]["off"]["frames"] == 32 and result["rows"]["off"]["pixel_share"] == 0.0678


# --- one seabed beyond the tile: the rings evaluate one noise field and meet without a seam -----------------------

LIPSCHITZ = 3.0 / RELIEF_WAVELENGTH_M  # per metre along x or y: smoothstep's slope (1.5) times a lattice step (2)


def beyond_edge(xy: np.ndarray, terrain) -> np.ndarray:
    """(n,) metres from the tile's rectangle out to each point (the distance that names a point's ring)."""
    xmin, xmax, ymin, ymax = terrain.extent
    return np.maximum(np.maximum(xmin - xy[:, 0], xy[:, 0] - xmax), np.maximum(ymin - xy[:, 1], xy[:, 1] - ymax))


terrains = st.builds(lambda style, seed, size, cells, relief: heightfield(np.random.default_rng(seed), style, size,
                                                                          cells, relief),
                     st.sampled_from(STYLES), st.integers(0, 2**31), st.floats(2.0, 60.0), st.integers(2, 96),
                     st.floats(0.05, 3.0))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), field=st.sampled_from([RELIEF, TONE]),
       xy=st.lists(st.tuples(st.floats(-5000.0, 5000.0), st.floats(-5000.0, 5000.0)), min_size=2, max_size=40),
       data=st.data())
def test_the_far_noise_is_a_function_of_the_seed_and_the_world_point_alone(seed, field, xy, data):
    """Any batch of points, in any order, split anywhere, gets each point the same value: no ring's evaluation can
    depend on which ring asks or what was asked before."""
    xy = np.asarray(xy)
    whole = far_noise(seed, field, xy)
    order = np.asarray(data.draw(st.permutations(range(len(xy)))))
    cut = data.draw(st.integers(1, len(xy) - 1))
    np.testing.assert_array_equal(far_noise(seed, field, xy[order]), whole[order])
    np.testing.assert_array_equal(np.concatenate([far_noise(seed, field, xy[order[:cut]]),
                                                  far_noise(seed, field, xy[order[cut:]])]), whole[order])
    assert np.isfinite(whole).all() and (np.abs(whole) <= 1.0).all()
    assert not np.array_equal(far_noise(seed, 1 - field, xy), whole)  # relief and tone are two fields


@settings(max_examples=20, deadline=None)
@given(terrain=terrains, reach=st.floats(3.0, 800.0))  # 3 m: some ring lies past the blend
def test_every_ring_beyond_the_blend_is_the_one_seabed_at_its_points(terrain, reach):
    """Past BLEND_M every ring's heights are exactly `far_seabed` at its vertices and its colours that encoded: the
    mesh is one function of (the terrain's seed, world point), whichever ring and whichever reach."""
    far = far_field.__wrapped__(terrain, reach)
    v = np.asarray(far.mesh.vertices)
    far_part = beyond_edge(v[:, :2], terrain) >= BLEND_M
    assert far_part.sum() >= 4
    z, rgb = far_seabed(seabed_of(terrain), v[far_part, :2])
    np.testing.assert_array_equal(v[far_part, 2], z)
    np.testing.assert_array_equal(np.asarray(far.mesh.visual.vertex_colors)[far_part, :3],
                                  encode_srgb8(np.clip(rgb, 0.0, 1.0)))
    # A farther reach adds rings outside and changes none of those both have.
    longer = far_field.__wrapped__(terrain, 2.5 * reach).mesh
    n = len(v)
    np.testing.assert_array_equal(np.asarray(longer.vertices)[:n], v)
    np.testing.assert_array_equal(np.asarray(longer.visual.vertex_colors)[:n], far.mesh.visual.vertex_colors)


@settings(max_examples=20, deadline=None)
@given(terrain=terrains, reach=st.floats(1.0, 800.0))
def test_neighbouring_rings_share_their_loop_and_the_seabed_runs_on_across_it(terrain, reach):
    """Each loop between two bands of triangles is one set of vertices and edges that both bands use (so heights
    and colours on it are the same seen from either band), and past the blend the heights and colours across a
    band change no faster than the one noise field can: no ring is a field of its own."""
    far = far_field.__wrapped__(terrain, reach)
    f, starts = np.asarray(far.mesh.faces), np.asarray(far.rings)
    band = np.searchsorted(starts, f.min(axis=1), side="right") - 1  # a face's band: from its inner loop outwards
    assert (np.searchsorted(starts, f.max(axis=1), side="right") - 1 == band + 1).all()

    def loop_edges(k: int, faces: np.ndarray) -> set:
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        on_loop = ((edges >= starts[k]) & (edges < starts[k + 1])).all(axis=1)
        return {tuple(e) for e in edges[on_loop]}

    for k in range(1, len(starts) - 2):
        ids = np.arange(starts[k], starts[k + 1])
        loop = {tuple(sorted((int(a), int(b)))) for a, b in zip(ids, np.roll(ids, -1))}
        assert loop_edges(k, f[band == k - 1]) == loop == loop_edges(k, f[band == k])
    v = np.asarray(far.mesh.vertices)
    seabed = seabed_of(terrain)
    tri = f[(beyond_edge(v[:, :2], terrain)[f] >= BLEND_M).all(axis=1)]
    a, b = tri.ravel(), np.roll(tri, 1, axis=1).ravel()
    step = np.abs(v[a, :2] - v[b, :2]).sum(axis=1)  # metres, |dx| + |dy|
    assert (np.abs(v[a, 2] - v[b, 2]) <= seabed.spread_z * LIPSCHITZ * step * (1 + 1e-9) + 1e-9).all()
    linear = decode_srgb8(np.asarray(far.mesh.visual.vertex_colors)[:, :3], np.float64)
    bound = seabed.mean_rgb * seabed.tone * LIPSCHITZ * step[:, None] + 0.01  # 0.01: 8-bit rounding at both ends
    assert (np.abs(linear[a] - linear[b]) <= bound).all()


def test_a_process_builds_each_terrains_far_field_once():
    """A render process keeps the far field of every terrain the example draws (30 with its styles, variants and
    materials): sampling its scenes twice over builds each one once, where a smaller cache rebuilt it for 40% of the
    frames (bench/results/cpu/far-field-cache)."""
    from seasynth.worker.frame.function import RenderSession

    spec = load_spec(EXAMPLE, {"frames": 120})
    session = RenderSession()
    far_field.cache_clear()
    keys = {session.scene(spec, i % spec.frames).terrain.key for i in range(2 * spec.frames)}
    info = far_field.cache_info()
    assert info.misses == len(keys) and info.hits == 2 * spec.frames - len(keys)
    assert len(keys) <= info.maxsize
