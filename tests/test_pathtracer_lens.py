"""The path tracer's thin lens (bench.pathtracer.PTLens, Mitsuba's `thinlens`) against seasynth's depth of field:
the same circle of confusion; a lens travels with a saved scene, and a pinhole scene's arrays are as before lenses."""

import dataclasses
import importlib.util
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

if importlib.util.find_spec("mitsuba") is None:  # only a missing Mitsuba skips
    pytest.skip("mitsuba is not installed (pip install -e '.[bench]')", allow_module_level=True)

from seasynth.bench.pathtracer import PTLens, PTScene, _sensor, load_mitsuba
from seasynth.bench.reference import load_scene, save_scene, scene_digest
from seasynth.worker.optics.dof import coc_radius_px

# Aperture samples that Mitsuba's concentric disc mapping sends to the aperture's rim.
RIM = ((1.0, 0.5), (0.0, 0.5), (0.5, 1.0), (0.5, 0.0), (1.0, 1.0), (0.0, 0.0))


def scene(fx: float, lens: PTLens | None, w: int = 64, h: int = 48) -> PTScene:
    K = np.array([[fx, 0.0, (w - 1) / 2], [0.0, fx, (h - 1) / 2], [0.0, 0.0, 1.0]])
    z3 = np.zeros(3)
    return PTScene(meshes=(), K=K, width=w, height=h, world_from_cam=np.eye(4), sigma_a=z3, sigma_s=z3, g=0.9,
                   surface_z=10.0, sun_dir_world=np.array([0.0, 0.0, 1.0]), sun_irradiance_rgb=z3,
                   sky_radiance_rgb=z3, lens=lens)


@settings(max_examples=25, deadline=None)
@given(fx=st.floats(30, 3000), focal_mm=st.floats(3, 100), n=st.floats(0.7, 16), focus=st.floats(0.3, 10),
       z=st.floats(0.2, 100))
def test_the_path_tracers_thin_lens_has_seasynths_circle_of_confusion(fx, focal_mm, n, focus, z):
    f = focal_mm / 1000
    mi = load_mitsuba()
    lens = PTLens(aperture_radius_m=f / (2 * n) * focus / (focus - f), focus_m=focus)
    description = _sensor(scene(fx, lens), 1000.0, mi)
    description.pop("medium")
    sensor = mi.load_dict(description)
    expected = float(coc_radius_px(np.array([[z]]), fx, f, n, focus)[0, 0])
    for aperture in RIM:
        # The ray through the image centre from the rim crosses depth z this far off the axis, in pinhole pixels:
        # the radius of the disc of film positions whose rays meet a point there.
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(*aperture))
        o = np.array([ray.o.x[0], ray.o.y[0], ray.o.z[0]], np.float64)
        d = np.array([ray.d.x[0], ray.d.y[0], ray.d.z[0]], np.float64)
        p = o + d * (z - o[2]) / d[2]
        assert math.isclose(math.hypot(p[0], p[1]) / z * fx, expected, rel_tol=1e-4, abs_tol=1e-4)


def test_a_lens_travels_with_its_scene_and_a_pinhole_scene_is_as_before(tmp_path):
    pinhole = scene(100.0, None)
    lens = dataclasses.replace(pinhole, lens=PTLens(aperture_radius_m=0.01, focus_m=1.5))
    save_scene(pinhole, tmp_path / "pinhole.npz")
    save_scene(lens, tmp_path / "lens.npz")
    with np.load(tmp_path / "pinhole.npz") as a:
        assert not any(k.startswith("lens") for k in a.files)  # the digests of stored references hold
    assert load_scene(tmp_path / "pinhole.npz").lens is None
    assert load_scene(tmp_path / "lens.npz").lens == lens.lens
    assert scene_digest(load_scene(tmp_path / "lens.npz")) == scene_digest(lens) != scene_digest(pinhole)
    with pytest.raises(ValueError, match="principal point"):
        off = dataclasses.replace(lens, K=lens.K + np.array([[0, 0, 3.0], [0, 0, 0], [0, 0, 0]]))
        _sensor(off, 100.0, load_mitsuba())
