"""The camera model (seasynth.service.camera_model): Snell's law ray by ray through a flat port and a dome, a centred
dome without distortion, pixel -> ray -> pixel round trips, Brown-Conrady inversion, and the spec's refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from spec_helpers import refusal

from seasynth.service.camera_model import CameraModel, distort, fold_radius, undistort
from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import parse_spec

INDEX = st.floats(1.0, 2.0)


def model_of(camera: dict) -> CameraModel:
    """The model of a camera section (a drawn distortion that folds the image is skipped)."""
    try:
        return CameraModel.from_spec(parse_spec({"camera": camera}).camera)
    except SpecError as err:
        assume("folds the image over" not in str(err))
        raise


@st.composite
def cameras(draw, kind=None, distorted=True):
    """A camera section: size, field of view, port (kind, glass, indices, dimensions) and a mild distortion."""
    kind = draw(st.sampled_from(["none", "flat", "dome"])) if kind is None else kind
    cam = {"width": draw(st.integers(16, 200)), "height": draw(st.integers(16, 200)),
           "hfov_deg": draw(st.floats(20.0, 120.0))}
    if kind != "none":
        port = {"kind": kind, "thickness_mm": draw(st.floats(1.0, 30.0)), "glass_index": draw(INDEX),
                "water_index": draw(INDEX), "distance_mm": draw(st.floats(1.0, 100.0))}
        if kind == "dome":
            port["radius_mm"] = port["thickness_mm"] + draw(st.floats(20.0, 150.0))
            port["pupil_offset_mm"] = draw(st.tuples(*[st.floats(-0.3, 0.3)] * 3)) if draw(st.booleans()) else (
                0.0, 0.0, 0.0)
            port["pupil_offset_mm"] = [c * (port["radius_mm"] - port["thickness_mm"]) for c in port["pupil_offset_mm"]]
        cam["port"] = port
    if distorted and draw(st.booleans()):
        cam["distortion"] = [draw(st.floats(-0.05, 0.05)), draw(st.floats(-0.02, 0.02)),
                             draw(st.floats(-0.005, 0.005)), draw(st.floats(-0.005, 0.005)), 0.0]
    return cam


def pixels(draw, cam: dict, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    u = np.array(draw(st.lists(st.floats(-0.5, cam["width"] - 0.5), min_size=n, max_size=n)))
    v = np.array(draw(st.lists(st.floats(-0.5, cam["height"] - 0.5), min_size=n, max_size=n)))
    return u, v


def sin_to(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """|sin| of the angle between unit rays d and unit normals n."""
    return np.linalg.norm(np.cross(d, n), axis=-1)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def assert_snell(m: CameraModel, a: np.ndarray, g: np.ndarray, w: np.ndarray, n1: np.ndarray, n2: np.ndarray):
    """Rays a (air) -> g (glass) -> w (water), (n, 3) unit, obey n sin = n' sin about the surfaces' normals n1, n2
    and stay in each plane of incidence."""
    np.testing.assert_allclose(1.0 * sin_to(a, n1), m.glass_index * sin_to(g, n1), atol=1e-9)
    np.testing.assert_allclose(m.glass_index * sin_to(g, n2), m.water_index * sin_to(w, n2), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(np.stack([a, g, n1], axis=1)), 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(np.stack([g, w, n2], axis=1)), 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_a_flat_port_bends_each_ray_by_snells_law_at_both_surfaces_in_the_plane_of_incidence(data):
    cam = data.draw(cameras(kind="flat"))
    m = model_of(cam)
    u, v = pixels(data.draw, cam)
    a = m.air_directions(u, v)
    o, w = m.pixel_rays(u, v)
    p1 = a * (m.distance_m / a[:, 2:3])  # where the air ray meets the inner plane
    g = unit(o - p1)  # its path through the glass to the water ray's origin
    z = np.broadcast_to([0.0, 0.0, 1.0], a.shape)
    np.testing.assert_allclose(o[:, 2], m.distance_m + m.thickness_m, rtol=1e-12)
    assert_snell(m, a, g, w, z, z)
    assert np.all(np.sum(a[:, :2] * w[:, :2], axis=1) >= 0) and np.all(w[:, 2] > 0)  # onwards, the same side


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_a_dome_bends_each_ray_by_snells_law_about_the_spheres_normals(data):
    cam = data.draw(cameras(kind="dome"))
    m = model_of(cam)
    u, v = pixels(data.draw, cam)
    a = m.air_directions(u, v)
    o, w = m.pixel_rays(u, v)
    ok = np.isfinite(w[:, 0])  # totally reflected rays are NaN: check the rest
    a, o, w = a[ok], o[ok], w[ok]
    c, inner = m.centre_m, m.radius_m - m.thickness_m
    s = -(a @ -c) + np.sqrt((a @ -c) ** 2 - (c @ c - inner**2))  # the air ray leaves the inner sphere
    p1 = s[:, None] * a
    g = unit(o - p1)
    n1, n2 = unit(p1 - c), unit(o - c)
    np.testing.assert_allclose(np.linalg.norm(o - c, axis=1), m.radius_m, rtol=1e-12)
    assert_snell(m, a, g, w, n1, n2)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_a_centred_dome_is_distortion_free_every_water_ray_passes_through_the_centre_as_the_pinholes(data):
    cam = data.draw(cameras(kind="dome", distorted=False))
    cam["port"]["pupil_offset_mm"] = [0.0, 0.0, 0.0]
    m = model_of(cam)
    u, v = pixels(data.draw, cam)
    o, w = m.pixel_rays(u, v)
    pinhole = unit(np.stack([(u - m.K[0, 2]) / m.K[0, 0], (v - m.K[1, 2]) / m.K[1, 1], np.ones_like(u)], axis=1))
    np.testing.assert_allclose(w, pinhole, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.cross(o, w), axis=1), 0.0, atol=1e-15)  # the line holds the centre
    np.testing.assert_allclose(m.project(o + 2.0 * w), np.stack([u, v], axis=1), atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_pixel_to_water_ray_to_pixel_round_trips(data):
    cam = data.draw(cameras())
    m = model_of(cam)
    u, v = pixels(data.draw, cam)
    o, w = m.pixel_rays(u, v)
    ok = np.isfinite(w[:, 0])
    t = np.array(data.draw(st.lists(st.floats(0.05, 50.0), min_size=len(u), max_size=len(u))))
    uv = m.project(o[ok] + t[ok, None] * w[ok])
    np.testing.assert_allclose(uv, np.stack([u, v], axis=1)[ok], atol=1e-5)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_water_clearance_is_zero_where_each_water_ray_starts_and_positive_along_it(data):
    """Every water ray starts on the port's outer surface (clearance 0) and runs out into the water; the pupil lies
    inside the housing."""
    cam = data.draw(cameras(kind=data.draw(st.sampled_from(["flat", "dome"]))))
    m = model_of(cam)
    u, v = pixels(data.draw, cam)
    o, w = m.pixel_rays(u, v)
    ok = np.isfinite(w[:, 0])
    np.testing.assert_allclose(m.water_clearance(o[ok]), 0.0, atol=1e-12)
    assert np.all(m.water_clearance(o[ok] + 0.01 * w[ok]) > 0) and m.water_clearance(np.zeros(3)) < 0
    assert np.all(np.isinf(model_of({**cam, "port": {"kind": "none"}}).water_clearance(o)))


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_undistortion_inverts_brown_conrady_to_its_tolerance(data):
    cam = data.draw(cameras(kind="none"))
    d = np.asarray(cam.get("distortion", [0.0] * 5))
    xy = np.array(data.draw(st.lists(st.floats(-0.8, 0.8), min_size=32, max_size=32))).reshape(2, 16)
    x, y = undistort(*distort(xy[0], xy[1], d), d)
    np.testing.assert_allclose(np.stack([x, y]), xy, atol=1e-9)
    xd, yd = distort(*undistort(xy[0], xy[1], d), d)
    assert np.abs(np.stack([xd, yd]) - xy).max() <= 1e-9


def test_points_the_camera_cannot_see_project_to_nan():
    m = model_of({"port": {"kind": "flat"}})
    uv = m.project(np.array([[0.0, 0.0, -1.0], [0.1, 0.0, 0.02], [0.0, 0.0, 1.0]]))
    assert np.isnan(uv[:2]).all() and np.allclose(uv[2], m.K[:2, 2])
    # k1 = -0.2 folds at r = 1 / sqrt(0.6): a point beyond would land back inside the image
    m = model_of({"distortion": [-0.2, 0.0, 0.0, 0.0, 0.0], "hfov_deg": 60.0})
    assert fold_radius(m.distortion) == pytest.approx(1 / np.sqrt(0.6), abs=1e-4)
    uv = m.project(np.array([[1.2, 0.0, 1.0], [1.4, 0.0, 1.0]]))
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()


@settings(max_examples=50, deadline=None)
@given(cameras())
def test_the_model_rebuilds_from_its_meta_record(cam):
    m = model_of(cam)
    again = CameraModel.from_record(m.record())
    u, v = np.meshgrid(np.arange(0.0, cam["width"], 7.0), np.arange(0.0, cam["height"], 5.0))
    for a, b in zip(m.pixel_rays(u, v), again.pixel_rays(u, v)):
        np.testing.assert_array_equal(a, b)


def test_a_flat_ports_slab_is_what_a_path_tracer_builds():
    slab = model_of({"port": {"kind": "flat", "distance_mm": 12.0, "thickness_mm": 8.0}}).slab()
    assert (slab.inner_m, slab.outer_m, slab.air_index) == pytest.approx((0.012, 0.020, 1.0))
    with pytest.raises(ValueError, match="'dome' is not a slab"):
        model_of({"port": {"kind": "dome"}}).slab()


@pytest.mark.parametrize(("camera", "path", "fragment"), [
    ({"port": {"kind": "flat", "thickness_mm": 0.0}}, "camera.port.thickness_mm", "greater than 0"),
    ({"port": {"kind": "flat", "glass_index": 0.9}}, "camera.port.glass_index", "greater than or equal to 1"),
    ({"port": {"kind": "flat", "water_index": 3.5}}, "camera.port.water_index", "less than or equal to 3"),
    ({"port": {"kind": "flat", "distance_mm": -1.0}}, "camera.port.distance_mm", "greater than 0"),
    ({"port": {"kind": "fisheye"}}, "camera.port.kind", "'none', 'flat' or 'dome'"),
    ({"port": {"kind": "dome", "radius_mm": 10.0}}, "camera.port", "thickness_mm 10.0 must be less than radius_mm"),
    ({"port": {"kind": "dome", "pupil_offset_mm": [0.0, 0.0, 45.0]}}, "camera.port", "outside the dome's inner"),
    ({"distortion": [0.1, 0.0, 0.0, 0.0]}, "camera.distortion.4", "Field required"),
    ({"distortion": [0.0, 0.0, 2.0, 0.0, 0.0]}, "camera.distortion", "p1 2.0 must lie within +-1.0"),
    ({"distortion": [-0.6, 0.0, 0.0, 0.0, 0.0], "hfov_deg": 100.0}, "camera.distortion", "folds the image over"),
])
def test_a_bad_port_or_distortion_is_refused_naming_the_field(camera, path, fragment):
    (line,) = refusal({"camera": camera})
    assert line.startswith(f"{path}: "), line
    assert fragment in line


@given(st.data())
def test_the_ports_transmittance_is_fresnels_at_each_surface_times_radiances_n_squared_law(data):
    cam = data.draw(cameras())
    m = model_of(cam)
    u, v = pixels(data.draw, cam)
    t = m.transmittance(u, v)
    if m.kind == "none":
        assert np.array_equal(t, np.ones_like(u))
        return
    ok = np.isfinite(t)
    law = (1.0 / m.water_index) ** 2
    assert np.all((t[ok] > 0) & (t[ok] <= law * (1 + 1e-12)))  # reflection only takes light away
    # at normal incidence Fresnel is ((n1 - n2) / (n1 + n2))^2 at each surface
    normal = 1 - ((1 - m.glass_index) / (1 + m.glass_index)) ** 2
    normal *= 1 - ((m.glass_index - m.water_index) / (m.glass_index + m.water_index)) ** 2
    if m.kind == "flat" or not np.any(m.centre_m):  # the axis pixel meets both surfaces head on
        K = m.K
        centre = m.transmittance(np.array([K[0, 2]]), np.array([K[1, 2]]))
        if not np.any(m.distortion[2:4]):  # tangential distortion moves the axis off the principal point
            assert np.allclose(centre, law * normal, rtol=1e-9)


def test_a_flat_ports_transmittance_falls_with_the_field_angle_and_is_the_n_squared_law_without_fresnel():
    m = model_of({"width": 64, "height": 48, "hfov_deg": 90.0, "port": {"kind": "flat"}})
    u = np.linspace(m.K[0, 2], 63.5, 20)
    t = m.transmittance(u, np.full_like(u, m.K[1, 2]))
    assert np.all(np.diff(t) < 0)
    same = model_of({"width": 64, "height": 48, "hfov_deg": 90.0,
                     "port": {"kind": "flat", "glass_index": 1.0, "water_index": 1.0}})
    assert np.allclose(same.transmittance(u, u * 0 + 20.0), 1.0, rtol=1e-12)
