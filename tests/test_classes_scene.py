"""Scenes of several target classes (seasynth.worker.scene.sample, .placement), over random specs: every object
where its class's placement says (on the seabed, sunk into it, above it in the water, schools abreast), no two
objects intersecting, counts drawn per class and recorded. Sampling needs no GL."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seasynth.service.spec.dataset import DatasetSpec, parse_spec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.scene.sample import Placed, Scene

KINDS = ("urchin", "rock", "coral", "seaweed", "clam")
EPS = 1e-9  # metres: rounding of the recomputed geometry


@pytest.fixture(scope="module")
def session():
    return RenderSession()  # not entered: no GL context, only the asset and terrain sources


def interval(lo: float, hi: float, width: float):
    return st.tuples(st.floats(lo, hi - width), st.floats(0, width)).map(lambda t: [t[0], t[0] + t[1]])


def placement():
    water = st.fixed_dictionaries(
        {"kind": st.just("water"), "height_m": interval(0.0, 1.0, 0.5), "pitch_deg": interval(-40, 40, 30),
         "roll_deg": interval(-40, 40, 30)},
        optional={"school": st.fixed_dictionaries({"size": st.tuples(st.integers(0, 2), st.integers(0, 3)).map(
            lambda t: [t[0], t[0] + t[1]]), "spacing_m": interval(0.01, 0.2, 0.1)})})
    buried = st.fixed_dictionaries({"kind": st.just("buried"), "sunk_fraction": interval(0.0, 1.0, 0.5)})
    return st.one_of(st.just("seabed"), buried, water)


@st.composite
def specs(draw) -> DatasetSpec:
    n = draw(st.integers(1, 3))
    classes = [{"class_name": f"C{k}", "assets": [{"procedural": draw(st.sampled_from(KINDS)), "variants": 2}],
                "count": sorted(draw(st.lists(st.integers(0, 4), min_size=2, max_size=2))),
                "scale": draw(interval(0.5, 3.0, 1.5)), "placement": draw(placement())} for k in range(n)]
    return parse_spec({
        "seed": draw(st.integers(0, 2**31)), "targets": classes,
        "distractors": {"count": sorted(draw(st.lists(st.integers(0, 5), min_size=2, max_size=2)))},
        "terrain": {"cells": 24, "variants": 2, "size_m": 6.0, "relief_m": draw(st.floats(0.0, 0.6)),
                    "far_field": False},
        "workspaces": {"targets": {"min": [-1.5, -1.5, -5.0], "max": [1.5, 1.5, 5.0]}},
        "materials": {"procedural": False}})


def world_vertices(p: Placed) -> np.ndarray:
    v = np.asarray(p.asset.mesh.vertices, dtype=np.float64)
    return v @ p.world_from_obj[:3, :3].T + p.world_from_obj[:3, 3]


def cylinder(p: Placed) -> tuple[np.ndarray, float, float, float]:
    """(anchor xy, radius, lowest z, highest z) measured afresh from the placed mesh; an object standing on or in
    the seabed reaches down to -inf (nothing may lie under it)."""
    v = world_vertices(p)
    anchor = p.world_from_obj[:2, 3]
    radius = float(np.linalg.norm(v[:, :2] - anchor, axis=1).max())
    grounded = p.placement is None or p.placement["kind"] != "water"
    return anchor, radius, -math.inf if grounded else float(v[:, 2].min()), float(v[:, 2].max())


def check_scene(spec: DatasetSpec, scene: Scene) -> None:
    objs = scene.objects
    assert [p.instance_id for p in objs] == list(range(1, len(objs) + 1))
    # Targets class by class in spec order, then the distractors.
    order = [spec.class_names.index(p.class_name) if p.role == "target" else len(spec.targets) for p in objs]
    assert order == sorted(order)
    # Counts drawn per class within its range (schools: times the school sizes), those left out not placed.
    assert [c[0] for c in scene.class_counts] == list(spec.class_names)
    for cls, (_, drawn, left) in zip(spec.targets, scene.class_counts):
        school = getattr(cls.placement, "school", None)
        lo, hi = (1, 1) if school is None else school.size
        assert cls.count[0] * lo <= drawn <= cls.count[1] * hi and 0 <= left <= drawn
        assert sum(p.class_name == cls.class_name for p in objs) == drawn - left
    # No two objects intersect: each lies in the cylinder over its footprint between its heights, and no two
    # such cylinders overlap.
    cyl = [cylinder(p) for p in objs]
    for i in range(len(objs)):
        for j in range(i):
            (a, ra, lo_a, hi_a), (b, rb, lo_b, hi_b) = cyl[i], cyl[j]
            apart = np.linalg.norm(a - b) >= ra + rb - EPS
            assert apart or hi_a <= lo_b + EPS or hi_b <= lo_a + EPS, (objs[i].instance_id, objs[j].instance_id)
    terrain = scene.terrain
    verts, normals = np.asarray(terrain.mesh.vertices), np.asarray(terrain.mesh.vertex_normals)
    for p, cls in ((p, spec.targets[spec.class_names.index(p.class_name)] if p.role == "target" else None)
                   for p in objs):
        kind = p.placement["kind"]
        T = p.world_from_obj
        up = T[:3, 2] / np.linalg.norm(T[:3, 2])
        if kind == "water":
            # Every vertex clears the seabed under it by at least the drawn height, which is in the class's range.
            h = p.placement["height_m"]
            assert cls.placement.height_m[0] <= h <= cls.placement.height_m[1]
            v = world_vertices(p)
            assert np.all(v[:, 2] - terrain.height_at(v[:, :2]) >= h - EPS)
            continue
        # On the seabed: the base's origin on a terrain vertex, upright along its normal; buried: moved down that
        # normal by the drawn fraction of the object's height.
        sunk = p.placement.get("sunk_fraction", 0.0)
        if kind == "buried":
            assert cls.placement.sunk_fraction[0] <= sunk <= cls.placement.sunk_fraction[1]
        height = float(np.ptp(np.asarray(p.asset.mesh.vertices)[:, 2])) * p.scale
        rest = T[:3, 3] + up * sunk * height
        k = int(np.argmin(np.linalg.norm(verts - rest, axis=1)))
        assert np.linalg.norm(verts[k] - rest) < 1e-9
        np.testing.assert_allclose(up, normals[k] / np.linalg.norm(normals[k]), atol=1e-9)
        if kind == "seabed":
            # The stated tolerance: the seabed covers a seabed object's base at most by as much as it rises above
            # the tangent plane at the anchor within the object's footprint (plus a terrain cell).
            v = world_vertices(p)
            radius = float(np.linalg.norm(v[:, :2] - rest[:2], axis=1).max())
            edge = 2 * spec.terrain.size_m / spec.terrain.cells
            near = verts[np.linalg.norm(verts[:, :2] - rest[:2], axis=1) <= radius + edge]
            rise = float(((near - rest) @ up / up[2]).max())
            xmin, xmax, ymin, ymax = terrain.extent  # beyond the tile's edge there is no seabed to cover it
            on_tile = v[(v[:, 0] >= xmin) & (v[:, 0] <= xmax) & (v[:, 1] >= ymin) & (v[:, 1] <= ymax)]
            cover = terrain.height_at(on_tile[:, :2]) - on_tile[:, 2]
            assert float(cover.max(initial=0.0)) <= max(rise, 0.0) + EPS


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(spec=specs(), index=st.integers(0, 50))
def test_random_multi_class_scenes_place_every_object_as_its_class_says_and_none_intersect(session, spec, index):
    scene = session.scene(spec, index)
    check_scene(spec, scene)
    again = session.scene(spec, index)  # seeded: the same scene again
    assert [(p.instance_id, p.class_name, p.world_from_obj.tobytes()) for p in again.objects] == \
        [(p.instance_id, p.class_name, p.world_from_obj.tobytes()) for p in scene.objects]
    assert again.class_counts == scene.class_counts


def test_a_school_lines_up_abreast_sharing_height_and_heading(session):
    spec = parse_spec({"seed": 4, "targets": [{"class_name": "Fish", "assets": [{"procedural": "clam"}],
                                               "count": [1, 1], "placement": {
                                                   "kind": "water", "height_m": [0.3, 0.6], "pitch_deg": [0, 0],
                                                   "roll_deg": [0, 0], "school": {"size": [4, 4],
                                                                                  "spacing_m": [0.1, 0.1],
                                                                                  "heading_jitter_deg": 0.0}}}],
                       "distractors": {"count": [0, 0]}, "terrain": {"relief_m": 0.0, "far_field": False}})
    placed = [sc for sc in (session.scene(spec, i) for i in range(10)) if len(sc.objects) == 4]
    assert placed, "no frame placed the whole school"
    for scene in placed:
        check_scene(spec, scene)
        heights = {p.placement["height_m"] for p in scene.objects}
        assert len(heights) == 1  # one height for the school
        heading = [math.atan2(p.world_from_obj[1, 0], p.world_from_obj[0, 0]) for p in scene.objects]
        np.testing.assert_allclose(np.diff(heading), 0.0, atol=1e-9)
        # Abreast: each member beside the one before it, its footprint spacing_m beyond its neighbour's.
        xy = np.array([p.world_from_obj[:2, 3] for p in scene.objects])
        side = np.array([-math.sin(heading[0]), math.cos(heading[0])])
        r = [p.footprint_m for p in scene.objects]
        np.testing.assert_allclose(np.diff(xy, axis=0) @ side, [r[k] + r[k + 1] + 0.1 for k in range(3)],
                                   atol=1e-9)


def test_a_single_mapping_and_a_list_of_it_draw_the_same_scenes(session):
    one = {"seed": 11, "targets": {"class_name": "Urchin", "count": [2, 5]}, "terrain": {"cells": 32}}
    listed = {**one, "targets": [one["targets"]]}
    a, b = parse_spec(one), parse_spec(listed)
    assert a == b
    for i in range(3):
        sa, sb = session.scene(a, i), session.scene(b, i)
        assert [p.world_from_obj.tobytes() for p in sa.objects] == [p.world_from_obj.tobytes() for p in sb.objects]
