"""Hard cases of scene sampling: cameras drawn inside the terrain or an object are drawn again or refused naming
the workspace, and values at the spec's caps render."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seasynth.service.camera_model import CameraModel
from seasynth.service.spec.dataset import load_spec, parse_spec
from seasynth.worker.scene.sample import CAMERA_CLEARANCE_M, CAMERA_TRIES, Placed, SceneError, sample_scene

# --- cameras drawn inside geometry ------------------------------------------------------------------------------

SMALL_WORLD = {
    "camera": {"width": 16, "height": 12},
    "terrain": {"styles": ["sand"], "variants": 1, "cells": 8, "size_m": 12.0, "relief_m": 0.25},
    "distractors": {"count": [0, 0]},
}
# The one target sits on the terrain vertex at (0, 0), and the camera looks at it.
TARGET_AT_ORIGIN = {"min": [-0.1, -0.1, -1.0], "max": [0.1, 0.1, 1.0]}
# name: (target scale, camera workspace straddling the geometry, camera workspace wholly inside it).
# Terrain heights lie in [0, 0.25] m; an urchin at scale 30 has a bounding sphere of radius 2-3.6 m centred
# about 1.5 m above the terrain, while at scale 1 it is 0.1 m across and barely in the way.
CAMERA_CASES = {
    "terrain": (1.0, {"min": [-5.0, -5.0, -0.6], "max": [5.0, 5.0, 0.6]},
                {"min": [-5.0, -5.0, -2.0], "max": [5.0, 5.0, -1.0]}),
    "object": (30.0, {"min": [-4.5, -4.5, 1.0], "max": [4.5, 4.5, 1.5]},
               {"min": [-0.5, -0.5, 1.0], "max": [0.5, 0.5, 1.5]}),
}


def small_spec(target_scale: float, camera_box: dict):
    return parse_spec({
        **SMALL_WORLD,
        "targets": {"count": [1, 1], "scale": [target_scale, target_scale]},
        "workspaces": {"camera": camera_box, "targets": TARGET_AT_ORIGIN, "look_at": TARGET_AT_ORIGIN},
    })


def bounding_sphere(p: Placed) -> tuple[np.ndarray, float]:
    v = np.asarray(p.asset.mesh.vertices)
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    radius = np.linalg.norm(v - centre, axis=1).max() * p.scale
    return p.world_from_obj[:3, :3] @ centre + p.world_from_obj[:3, 3], radius


@pytest.mark.parametrize("inside", list(CAMERA_CASES))
def test_a_camera_drawn_inside_geometry_is_drawn_again(render_session, inside):
    scale, straddling, _ = CAMERA_CASES[inside]
    spec = small_spec(scale, straddling)
    near = spec.camera.clip[0]
    redrawn = 0
    for index in range(12):
        scene = render_session.scene(spec, index)
        eye = scene.world_from_cam[:3, 3]
        [target] = scene.objects
        centre, radius = bounding_sphere(target)
        assert radius > 2.0 if inside == "object" else radius < 0.2
        assert eye[2] >= scene.terrain.height_at(eye[None, :2])[0] + CAMERA_CLEARANCE_M + near
        assert np.linalg.norm(eye - centre) > radius + CAMERA_CLEARANCE_M + near
        assert 1 <= scene.camera_tries < CAMERA_TRIES
        redrawn += scene.camera_tries > 1
        # The redraws come from the frame's own generator: the same frame is the same scene.
        again = render_session.scene(spec, index)
        assert again.camera_tries == scene.camera_tries
        np.testing.assert_array_equal(again.world_from_cam, scene.world_from_cam)
    assert redrawn >= 3


@pytest.mark.parametrize("inside", list(CAMERA_CASES))
def test_a_camera_workspace_wholly_inside_geometry_is_refused_naming_it(render_session, inside):
    scale, _, wholly_inside = CAMERA_CASES[inside]
    spec = small_spec(scale, wholly_inside)
    rng = np.random.default_rng(0)
    with pytest.raises(SceneError, match=rf"^workspaces\.camera: .* {CAMERA_TRIES} draws"):
        sample_scene(spec, rng, render_session.asset_for, render_session.terrain_for)


@pytest.mark.parametrize("x", [0.0, 1.7, -2.5])
def test_a_camera_workspace_on_its_look_at_point_is_refused_saying_so(render_session, x):
    point = {"min": [x, 0.5, 1.2], "max": [x, 0.5, 1.2]}
    spec = parse_spec({**SMALL_WORLD, "targets": {"count": [0, 0]}, "camera": {"width": 16, "height": 12,
                                                                               "look_at_jitter_m": 0.0},
                       "workspaces": {"camera": point, "look_at": point}})
    with pytest.raises(SceneError, match=rf"^workspaces\.camera: all {CAMERA_TRIES} positions drawn lie within 1 mm "
                                         r"of the point the camera looks at .*no direction to look in"):
        sample_scene(spec, np.random.default_rng(0), render_session.asset_for, render_session.terrain_for)



@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flat=st.booleans(), length_mm=st.floats(5.0, 600.0), thickness_mm=st.floats(1.0, 40.0),
       offset=st.tuples(*[st.floats(-0.3, 0.3)] * 3), low=st.floats(0.0, 0.5), index=st.integers(0, 10**6))
def test_nothing_lies_inside_a_ports_housing(render_session, flat, length_mm, thickness_mm, offset, low, index):
    """The housing a port's rays cross before they reach the water stays CAMERA_CLEARANCE_M clear of the terrain
    and every object's bounding sphere, on every ray of the image, however long the port; a workspace that leaves
    no room for it is refused naming the housing."""
    if flat:
        port = {"kind": "flat", "distance_mm": length_mm, "thickness_mm": thickness_mm}
    else:
        inner = length_mm - min(thickness_mm, length_mm / 2)
        port = {"kind": "dome", "radius_mm": length_mm, "thickness_mm": length_mm - inner,
                "pupil_offset_mm": [c * inner for c in offset]}
    spec = parse_spec({**SMALL_WORLD, "camera": {"width": 16, "height": 12, "port": port},
                       "targets": {"count": [1, 1], "scale": [3.0, 3.0]},
                       "workspaces": {"camera": {"min": [-4.0, -4.0, low], "max": [4.0, 4.0, low + 0.6]},
                                      "targets": TARGET_AT_ORIGIN, "look_at": TARGET_AT_ORIGIN}})
    housing = CameraModel.from_spec(spec.camera).housing_points()
    reach = np.linalg.norm(housing, axis=1).max()
    assert reach >= (length_mm + thickness_mm if flat else 0.0) * 1e-3 * (1 - 1e-9)
    try:
        scene = render_session.scene(spec, index)
    except SceneError as e:
        assert "camera.port's housing" in str(e)
        return
    T = scene.world_from_cam
    p = housing @ T[:3, :3].T + T[:3, 3]
    assert np.all(p[:, 2] >= scene.terrain.height_at(p[:, :2]) + CAMERA_CLEARANCE_M)
    [target] = scene.objects
    centre, radius = bounding_sphere(target)
    assert np.all(np.linalg.norm(p - centre, axis=1) > radius + CAMERA_CLEARANCE_M)


# Values at the spec's caps (seasynth.service.spec.types.MAX_MAGNITUDE and the per-field bounds): beyond them the spec refuses
# (tests/test_spec_refusals.py); at them a frame renders, its float32 light never overflowing to inf or NaN.
AT_THE_CAPS = {
    "sun": ("urchins", {"lighting.sun_intensity": [1e6, 1e6]}),
    "lamp-far-and-bright": ("night-dive", {"lighting.lamps": [{"offset_m": [1e6, 1e6, -1e6],
                                                                "intensity": [1e6, 1e6]}]}),
    "lamp-bright": ("night-dive", {"lighting.lamps": [{"intensity": [1e6, 1e6]}]}),
    "water-100x": ("urchins", {"water.beta_jitter": [100.0, 100.0]}),
    "widest-intrinsics": ("urchins", {"camera": {"width": 32, "height": 24, "intrinsics": {
        "fx": 1.41, "fy": 1.06, "cx": 1e6, "cy": -1e6}}}),
    "clip": ("urchins", {"camera.clip": [1e-6, 1e6]}),
    "look-at-jitter": ("urchins", {"camera.look_at_jitter_m": 100.0}),
    # and at the least floats above 0 the spec takes
    "least-target-scale": ("urchins", {"targets.scale": [5e-324, 1e-154], "targets.count": [2, 2]}),
    "least-terrain-size": ("urchins", {"terrain.size_m": 5e-324}),
    "least-particle-diameter": ("urchins", {"water.particles": {"enabled": True, "diameter_mm": [5e-324, 1.0]}}),
    "least-sensor-gain": ("urchins", {"noise.full_well_e": 1e7, "noise.gain": 5e-324}),
}


@pytest.mark.parametrize("name", list(AT_THE_CAPS))
def test_values_at_the_specs_caps_render(render_session, name):
    import io
    import json

    from PIL import Image

    example, changes = AT_THE_CAPS[name]
    spec = load_spec(f"examples/{example}.yaml", {"camera.width": 32, "camera.height": 24, "frames": 1,
                                                  "quality": "draft", **changes})
    files = render_session.frame_files(spec, 0)
    assert np.asarray(Image.open(io.BytesIO(files["image_2/000000.png"]))).shape == (24, 32, 3)

    def refuse(constant: str):
        raise AssertionError(f"{name}: meta holds {constant}")

    json.loads(files["meta/000000.json"], parse_constant=refuse)
