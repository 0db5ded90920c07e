"""bench/blender.py's conversions to Blender (camera, sun, water) and its scene export, without bpy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from seasynth.bench.blender import PAPER, export_frame, paper_volume
from seasynth.bench.blender_side import BLENDER_FROM_KITTI, blender_camera, blender_project, sun_matrix, volume_settings

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_centred_camera_known_values():
    """f = 400 px over 640 px is 22.5 mm over Blender's 36 mm sensor; a centred K has no shift; identity pose gives
    a Blender camera looking down world +z (KITTI forward) with its up along world -y (KITTI down is -up)."""
    K = np.array([[400.0, 0.0, 319.5], [0.0, 400.0, 239.5], [0.0, 0.0, 1.0]])
    cam = blender_camera(K, 640, 480, np.eye(4))
    assert cam.lens_mm == pytest.approx(22.5, abs=1e-12)
    assert cam.shift_x == 0.0 and cam.shift_y == 0.0
    np.testing.assert_array_equal(cam.matrix_world, np.diag([1.0, -1.0, -1.0, 1.0]))
    looks = cam.matrix_world[:3, :3] @ [0.0, 0.0, -1.0]
    up = cam.matrix_world[:3, :3] @ [0.0, 1.0, 0.0]
    np.testing.assert_array_equal(looks, [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(up, [0.0, -1.0, 0.0])


def test_off_centre_principal_point_known_shifts():
    """cx 20 px left of centre is a shift of +20/640 (the frustum moves right); cy 30 px below centre is +30/640."""
    K = np.array([[500.0, 0.0, 299.5], [0.0, 500.0, 269.5], [0.0, 0.0, 1.0]])
    cam = blender_camera(K, 640, 480, np.eye(4))
    assert cam.shift_x == pytest.approx(20.0 / 640.0, abs=1e-15)
    assert cam.shift_y == pytest.approx(30.0 / 640.0, abs=1e-15)
    # The optical axis lands on (cx, cy), and the image corners' rays on the corner pixels' centres.
    axis = blender_project(cam, 640, 480, np.array([[0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(axis, [[299.5, 269.5]], atol=1e-12)


def test_blender_projection_equals_k_projection_for_any_pose():
    """Blender's pinhole with the exported settings puts every point where K puts it (the bench also checks this
    in Blender itself, through bpy_extras, and records camera_check_px)."""
    rng = np.random.default_rng(3)
    K = np.array([[612.0, 0.0, 301.25], [0.0, 612.0, 250.75], [0.0, 0.0, 1.0]])
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3], world_from_cam[:3, 3] = _rotation(rng), rng.uniform(-3, 3, 3)
    pc = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-2, 2, 50), rng.uniform(0.5, 9, 50)])  # KITTI camera
    pw = pc @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    uv = pc @ K.T
    cam = blender_camera(K, 640, 480, world_from_cam)
    np.testing.assert_allclose(blender_project(cam, 640, 480, pw), uv[:, :2] / uv[:, 2:], atol=1e-9)
    np.testing.assert_array_equal(cam.matrix_world, world_from_cam @ BLENDER_FROM_KITTI)


def test_non_square_pixels_are_refused_by_name():
    K = np.array([[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="fx 500.0 != fy 510.0"):
        blender_camera(K, 640, 480, np.eye(4))


@pytest.mark.parametrize("sun_dir", [[0.3, -0.2, 0.9], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
def test_sun_lamp_shines_away_from_the_sun(sun_dir):
    """A rotation whose local +z is the unit vector to the sun, so the lamp's light (local -z) travels from it."""
    m = sun_matrix(np.array(sun_dir))
    r = m[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    unit = np.array(sun_dir) / np.linalg.norm(sun_dir)
    np.testing.assert_allclose(r @ [0.0, 0.0, -1.0], -unit, atol=1e-12)
    np.testing.assert_array_equal(m[:3, 3], 0.0)


def test_volume_nodes_give_back_the_coefficients():
    """Blender's absorption is density x (1 - color), its scattering density x color."""
    a, b = np.array([0.3, 0.08, 0.13]), np.array([0.857, 1.1, 1.43])
    v = volume_settings(a, b)
    (ca, da), (cs, ds) = v["absorption"], v["scatter"]
    np.testing.assert_allclose(da * (1.0 - np.array(ca)), a, rtol=1e-12)
    np.testing.assert_allclose(ds * np.array(cs), b, rtol=1e-12)
    assert max(cs) == 1.0 and min(ca) == 0.0  # colours within [0, 1]


def test_paper_volume_extinction_is_beta_with_the_types_albedo():
    beta = np.array([0.34, 0.2, 0.22])
    a_type, b_type = np.array([0.3, 0.08, 0.13]), np.array([0.857, 1.1, 1.43])
    a, b = paper_volume(beta, a_type, b_type)
    np.testing.assert_allclose(a + b, beta, rtol=1e-12)
    np.testing.assert_allclose(b / (a + b), b_type / (a_type + b_type), rtol=1e-12)


def test_export_frame_is_the_frames_own_scene():
    """The exported arrays are the draw items placed in the world, their albedo as seasynth shades it, the frame's
    camera, sun and water: checked item by item against the session's own scene."""
    from seasynth.service.spec.dataset import load_spec
    from seasynth.service.water import jerlov_absorption, jerlov_scattering
    from seasynth.worker.frame.function import RenderSession

    spec = load_spec(EXAMPLE, {"camera.width": 160, "camera.height": 120, "terrain.cells": 24,
                               "terrain.variants": 1, "distractors.count": [1, 2], "targets.count": [1, 2],
                               **PAPER})
    session = RenderSession()  # scenes only: no GL
    data = export_frame(session, spec, 1)
    scene = session.scene(spec, 1)
    items = session.draw_items(scene)
    assert data["vertex_counts"].tolist() == [len(it.mesh.vertices) for it in items]
    assert data["face_counts"].tolist() == [len(it.mesh.faces) for it in items]
    v0 = f0 = 0
    for it in items:
        n, m = len(it.mesh.vertices), len(it.mesh.faces)
        M = it.world_from_obj
        placed = it.mesh.vertices.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
        np.testing.assert_allclose(data["vertices"][v0:v0 + n], placed, atol=1e-5)
        np.testing.assert_array_equal(data["faces"][f0:f0 + m], it.mesh.faces)
        shaded = np.clip(it.mesh.albedo * it.albedo_scale + it.albedo_bias, 0.0, 1.0)
        np.testing.assert_allclose(data["albedo"][v0:v0 + n], shaded, atol=1e-7)
        v0, f0 = v0 + n, f0 + m
    assert v0 == len(data["vertices"]) and f0 == len(data["faces"])
    np.testing.assert_array_equal(data["K"], np.asarray(spec.camera.K()))
    assert data["size"].tolist() == [160, 120]
    np.testing.assert_array_equal(data["world_from_cam"], scene.world_from_cam)
    np.testing.assert_array_equal(data["sun_dir_world"], scene.lighting.sun_dir_world)
    assert float(data["sun_intensity"]) == scene.lighting.sun_intensity
    assert float(data["ambient"]) == scene.lighting.ambient
    a, b = data["absorption"], data["scattering"]
    np.testing.assert_allclose(a + b, scene.water.beta_D, rtol=1e-12)
    albedo = jerlov_scattering(scene.water_type) / (jerlov_absorption(scene.water_type)
                                                    + jerlov_scattering(scene.water_type))
    np.testing.assert_allclose(b / (a + b), albedo, rtol=1e-12)
    assert float(data["surface_z"]) == pytest.approx(spec.workspaces.camera.max[2] + 0.1)
    # Every exported vertex K puts in the image, Blender's camera puts at the same pixel.
    cam = blender_camera(data["K"], 160, 120, data["world_from_cam"])
    cam_from_world = np.linalg.inv(data["world_from_cam"])
    pc = data["vertices"].astype(np.float64) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    front = pc[:, 2] > 0.1
    uv = pc[front] @ data["K"].T
    np.testing.assert_allclose(blender_project(cam, 160, 120, data["vertices"][front]), uv[:, :2] / uv[:, 2:],
                               atol=1e-6)
