"""The lens effects (seasynth.worker.optics): depth of field, motion blur and the rolling shutter, vignetting."""

from __future__ import annotations

import io
import json
import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from seasynth.service.spec.dataset import load_spec, parse_spec
from seasynth.worker.optics.base import Shot
from seasynth.worker.optics.dof import MAX_RADIUS_PX, DepthOfField, coc_radius_px, gather_blur
from seasynth.worker.optics.motion import (
    MAX_INSTANTS,
    MotionBlur,
    frame_motion,
    instant_count,
    instants,
    pose_at,
    row_weights,
    streak_px,
)
from seasynth.worker.optics.vignetting import Vignetting, vignetting_gain
from seasynth.worker.render import RenderResult, View
from seasynth.worker.scene.trajectory import vehicle_state

EXAMPLE = "examples/urchins.yaml"
SMALL = {"camera.width": 64, "camera.height": 48, "outputs.meta": True, "outputs.instance": True,
         "outputs.range": True}
sides = st.integers(9, 41)
seconds = st.one_of(st.just(0.0), st.floats(1e-5, 0.5))  # an exposure or readout time: none, or one


def camera(width: int, height: int, hfov_deg: float, cx: float | None = None, cy: float | None = None) -> View:
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    return View(K=K, width=width, height=height, cam_from_world=np.eye(4), near=0.05, far=100.0)


def ray_norm(view: View) -> np.ndarray:
    """(h, w) float64: |K^-1 (u, v, 1)|, range over z-depth at each pixel centre."""
    u, v = np.meshgrid((np.arange(view.width) - view.K[0, 2]) / view.K[0, 0],
                       (np.arange(view.height) - view.K[1, 2]) / view.K[1, 1])
    return np.sqrt(1 + u**2 + v**2)


def shot(spec, view: View) -> Shot:
    return Shot(spec=spec, index=0, scene=None, view=view, render_view=view, items=[])


def result(image: np.ndarray, range_m: np.ndarray) -> RenderResult:
    h, w = range_m.shape
    return RenderResult(image=image, clean=image.copy(), instance=np.zeros((h, w), np.uint32), range_m=range_m)


# --- depth of field ---------------------------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(fx=st.floats(50, 5000), focal_mm=st.floats(2, 100), n=st.floats(0.7, 22), focus=st.floats(0.3, 20),
       z=st.lists(st.floats(0.05, 1000), min_size=1, max_size=20))
def test_circle_of_confusion_is_the_thin_lens_s(fx, focal_mm, n, focus, z):
    f = focal_mm / 1000
    z = np.array(z + [math.inf])
    r = coc_radius_px(z.reshape(1, -1), fx, f, n, focus)[0].astype(np.float64)
    # The thin lens: image distances v = 1 / (1/f - 1/z); a point's cone of aperture f/N meets the sensor (at the
    # focused image distance) in a disc of diameter (f/N) |v_s - v| / v; pixels are f / fx wide.
    with np.errstate(divide="ignore"):
        v = 1 / (1 / f - 1 / z)
    v_s = 1 / (1 / f - 1 / focus)
    expected = np.where(z > f, (f / n) * np.abs(v_s - v) / v / (f / fx) / 2, np.nan)
    ok = np.isfinite(expected)
    np.testing.assert_allclose(r[ok], expected[ok], rtol=1e-5, atol=1e-6)
    order = np.argsort(np.abs(1 / z[ok] - 1 / focus))  # more defocus (in dioptres), larger disc
    assert np.all(np.diff(r[ok][order]) >= -1e-4 * r[ok].max())


@settings(max_examples=30, deadline=None)
@given(w=sides, h=sides, hfov=st.floats(30, 120), n=st.floats(1, 16), focus=st.floats(0.3, 10),
       seed=st.integers(0, 2**32 - 1))
def test_a_plane_at_the_focus_distance_stays_sharp_to_the_byte(w, h, hfov, n, focus, seed):
    view = camera(w, h, hfov)
    spec = parse_spec({"camera": {"width": w, "height": h, "hfov_deg": hfov, "aperture_f": n, "focus_m": focus,
                                  "sensor_width_mm": 36.0}})
    range_m = (focus * ray_norm(view)).astype(np.float32)  # the plane z = focus_m
    image = np.random.default_rng(seed).uniform(0, 1, (h, w, 3)).astype(np.float32)
    s = shot(spec, view)
    out = DepthOfField().develop(s, result(image, range_m))
    assert out.image.tobytes() == image.tobytes() and out.clean.tobytes() == image.tobytes()
    assert s.record["depth_of_field"]["max_coc_radius_px"] <= 0.5


@settings(max_examples=40, deadline=None)
@given(radius=st.floats(0.6, MAX_RADIUS_PX), size=st.integers(15, 41))
def test_a_defocused_point_spreads_over_its_disc_and_no_further(radius, size):
    c = size // 2
    image = np.zeros((size, size, 3), np.float32)
    image[c, c] = 1.0
    r = np.full((size, size), radius, np.float32)
    (out,) = gather_blur([image], r, np.ones((size, size), np.float32))
    yy, xx = np.mgrid[:size, :size]
    d = np.hypot(yy - c, xx - c)
    lit = out[..., 0] > 0
    assert np.array_equal(lit, d < radius + 0.5)  # the anti-aliased disc of radius r about the point
    # A uniform plane stays uniform: the weights are normalised.
    (flat,) = gather_blur([np.full_like(image, 0.25)], r, np.ones((size, size), np.float32))
    np.testing.assert_allclose(flat, 0.25, rtol=1e-5)


@settings(max_examples=30, deadline=None)
@given(radius=st.floats(1, MAX_RADIUS_PX), split=st.integers(3, 20), seed=st.integers(0, 2**32 - 1))
def test_a_sharp_foreground_edge_keeps_the_blurred_background_off_it(radius, split, seed):
    h, w = 24, 24
    image = np.random.default_rng(seed).uniform(0, 1, (h, w, 3)).astype(np.float32)
    z = np.full((h, w), 10.0, np.float32)
    z[:, :split] = 1.0  # in focus, in front
    r = np.where(z > 1, radius, 0.0).astype(np.float32)
    (out,) = gather_blur([image], r, z)
    assert out[:, :split].tobytes() == image[:, :split].tobytes()
    assert not np.array_equal(out[:, split:], image[:, split:])


def test_depth_of_field_moves_no_geometry(render_session):
    spec = load_spec(EXAMPLE, {**SMALL, "outputs.labels": True})
    dof = load_spec(EXAMPLE, {**SMALL, "outputs.labels": True, "camera.aperture_f": 1.0, "camera.focus_m": 0.3,
                              "camera.sensor_width_mm": 90.0})
    a, b = render_session.frame_files(spec, 2), render_session.frame_files(dof, 2)
    for part in ("label_2/000002.txt", "instance/000002.png", "range/000002.npy", "calib/000002.txt"):
        assert a[part] == b[part], part
    assert a["image_2/000002.png"] != b["image_2/000002.png"]
    assert json.loads(b["meta/000002.json"])["optics"]["depth_of_field"]["max_coc_radius_px"] > 1


# --- vignetting -------------------------------------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(w=sides, h=sides, hfov=st.floats(20, 150), s=st.floats(0.01, 8), seed=st.integers(0, 2**32 - 1))
def test_vignetting_keeps_the_centre_and_darkens_corners_by_cos4(w, h, hfov, s, seed):
    view = camera(w, h, hfov, cx=float(w // 2), cy=float(h // 2))  # the principal point on a pixel centre
    spec = parse_spec({"camera": {"width": w, "height": h, "vignetting": s}})
    image = np.random.default_rng(seed).uniform(0.01, 1, (h, w, 3)).astype(np.float32)
    out = Vignetting().develop(shot(spec, view), result(image, np.ones((h, w), np.float32))).image
    assert out[h // 2, w // 2].tobytes() == image[h // 2, w // 2].tobytes()
    f = view.K[0, 0]
    for v, u in ((0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)):
        theta = math.atan(math.hypot(u - w // 2, v - h // 2) / f)
        np.testing.assert_allclose(out[v, u], image[v, u] * math.cos(theta) ** (4 * s), rtol=2e-5)
    assert np.all(np.diff(vignetting_gain(view.K, w, h, s)[h // 2, w // 2:]) <= 0)  # falls off the axis


# --- motion blur --------------------------------------------------------------------------------------------------

@settings(max_examples=50, deadline=None)
@given(span=st.floats(1e-4, 1), n=st.integers(1, MAX_INSTANTS // 2).map(lambda k: 2 * k + 1),
       exposure=seconds, readout=seconds, h=st.integers(8, 64))
def test_instants_and_row_weights(span, n, exposure, readout, h):
    span = exposure + readout if exposure + readout > 0 else span
    t = instants(span, n)
    assert t[n // 2] == 0.0 and np.all(np.diff(t) > 0) and abs(t[0] + span / 2 - span / n / 2) < 1e-12
    w = row_weights(t, span, h, exposure, readout)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-6)
    if readout == 0:  # a global shutter: every row the same weights
        assert np.all(w == w[0])
    if exposure == 0:  # an instantaneous row: one instant each, top to bottom in time
        assert np.all(np.sort(w, axis=1)[:, :-1] == 0)
        assert np.all(np.diff(np.argmax(w, axis=1)) >= 0)


@settings(max_examples=50, deadline=None)
@given(w=sides, h=sides, hfov=st.floats(30, 120), z=st.floats(0.2, 50), v=st.floats(-2, 2), t=st.floats(1e-3, 0.1))
def test_streak_of_a_sideways_move_past_a_plane_is_fx_v_t_over_z(w, h, hfov, z, v, t):
    view = camera(w, h, hfov)
    range_m = z * ray_norm(view)
    ends = [pose_at(np.eye(4), np.array([v, 0.0, 0.0]), np.zeros(3), s) for s in (-t / 2, t / 2)]
    assert math.isclose(streak_px(view, range_m, *ends), view.K[0, 0] * abs(v) * t / z, rel_tol=1e-6, abs_tol=1e-9)
    n = instant_count(streak_px(view, range_m, *ends))
    assert n % 2 == 1 and n <= MAX_INSTANTS


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), index=st.integers(0, 10**5), v=st.tuples(st.floats(0, 3), st.floats(0, 3)),
       rate=st.tuples(st.floats(0, 90), st.floats(0, 90)))
def test_a_random_frame_s_motion_is_drawn_in_its_ranges_from_its_own_stream(seed, index, v, rate):
    v, rate = tuple(sorted(v)), tuple(sorted(rate))
    spec = parse_spec({"seed": seed, "camera": {"exposure_s": 0.01, "velocity_m_s": list(v),
                                                "angular_rate_deg_s": list(rate)}})
    velocity, omega = frame_motion(spec, index)
    again = frame_motion(spec, index)
    assert velocity.tobytes() == again[0].tobytes() and omega.tobytes() == again[1].tobytes()
    assert v[0] - 1e-9 <= np.linalg.norm(velocity) <= v[1] + 1e-9
    assert math.radians(rate[0]) - 1e-9 <= np.linalg.norm(omega) <= math.radians(rate[1]) + 1e-9


@settings(max_examples=20, deadline=None)
@given(index=st.integers(0, 10**4), speed=st.floats(0.05, 5), heave=st.floats(0, 2), rate=st.floats(0.1, 20))
def test_a_survey_frame_moves_at_its_trajectorys_velocity(index, speed, heave, rate):
    spec = parse_spec({"camera": {"exposure_s": 0.01, "velocity_m_s": [9.0, 9.0]},
                       "trajectory": {"kind": "lawnmower", "speed_m_s": speed, "heave_m": heave, "rate_hz": rate}})
    velocity, omega = frame_motion(spec, index)
    state = vehicle_state(spec.trajectory, index)
    assert velocity.tobytes() == state.velocity_world.tobytes() and omega.tobytes() == state.angular_rate_world.tobytes()


def test_no_motion_or_no_exposure_is_no_blur_to_the_byte(render_session):
    off = render_session.frame_files(load_spec(EXAMPLE, SMALL), 1)
    for extra in ({"camera.exposure_s": 0.0, "camera.velocity_m_s": [1.0, 2.0]},  # no exposure: the effect is off
                  {"camera.exposure_s": 0.05}):  # an exposure without motion: one instant
        files = render_session.frame_files(load_spec(EXAMPLE, {**SMALL, **extra}), 1)
        assert sorted(files) == sorted(off)
        for part in files:
            if part != "meta/000001.json" or "camera.velocity_m_s" in extra:
                assert files[part] == off[part], (extra, part)


def test_a_blurred_frame_keeps_the_mid_exposure_labels_and_geometry(render_session):
    base = {**SMALL, "outputs.labels": True, "outputs.clean": True}
    moving = {**base, "camera.exposure_s": 0.03, "camera.velocity_m_s": [1.0, 1.0],
              "camera.angular_rate_deg_s": [20.0, 20.0]}
    still, blurred = (render_session.frame_files(load_spec(EXAMPLE, o), 4) for o in (base, moving))
    record = json.loads(blurred["meta/000004.json"])["optics"]["motion_blur"]
    assert record["instants"] >= 3 and record["streak_px"] > 1
    for part in ("label_2/000004.txt", "instance/000004.png", "range/000004.npy", "calib/000004.txt"):
        assert still[part] == blurred[part], part
    for part in ("image_2/000004.png", "clean/000004.png"):
        assert still[part] != blurred[part], part
    rolling = load_spec(EXAMPLE, {**moving, "camera.exposure_s": 0.0, "camera.readout_s": 0.05})
    files = render_session.frame_files(rolling, 4)
    rec = json.loads(files["meta/000004.json"])["optics"]["motion_blur"]
    assert rec["readout_s"] == 0.05 and rec["instants"] >= 3
    mid = np.load(io.BytesIO(still["range/000004.npy"]))
    skewed = np.load(io.BytesIO(files["range/000004.npy"]))
    # The middle rows are read at the frame's time; the top and bottom ones at other instants.
    h = mid.shape[0]
    assert not np.array_equal(skewed[0], mid[0]) or not np.array_equal(skewed[h - 1], mid[h - 1])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), speed=st.floats(0.2, 3), exposure=seconds, readout=seconds,
       h=st.integers(8, 40))
def test_each_row_averages_the_instants_of_its_window_and_takes_its_labels_from_the_nearest(seed, speed, exposure,
                                                                                             readout, h):
    spec = parse_spec({"seed": seed, "camera": {"width": 16, "height": h, "exposure_s": exposure, "readout_s": readout,
                                                "velocity_m_s": [speed, speed]}})
    assume(exposure + readout > 1e-3)  # a streak of at least a few hundredths of a pixel
    view = camera(16, h, 60.0)
    velocity, _ = frame_motion(spec, 0)
    times: list[float] = []

    def render(v: View, items) -> RenderResult:
        """Each pixel holds the instant's time (the camera's travel along the velocity over the speed); its
        instance ids the call's number; everything 2 m away."""
        t = float(np.linalg.inv(v.cam_from_world)[:3, 3] @ velocity) / speed**2
        times.append(t)
        full = np.full((h, 16), len(times), np.uint32)
        return RenderResult(image=np.full((h, 16, 3), t, np.float32), clean=None, instance=full,
                            range_m=np.full((h, 16), 2.0, np.float32))

    s = shot(spec, view)
    out = MotionBlur().expose(s, render)
    n = s.record["motion_blur"]["instants"]
    assert len(times) == n and n >= 3 and times[0] == 0.0  # the middle instant first: the frame's own view
    centre = (np.arange(h) / (h - 1) - 0.5) * readout
    cell = (exposure + readout) / n
    # A row's window [c - T/2, c + T/2] averaged over cells of the instants: its mean time is c, to within a cell.
    assert np.all(np.abs(out.image[:, 0, 0] - centre) <= cell / 2 + 1e-6)
    nearest = np.array(times)[out.instance[:, 0] - 1]
    assert np.all(np.abs(nearest - centre) <= cell / 2 + 1e-9)  # labels from the instant nearest the row's centre
    if readout == 0:
        assert np.all(out.instance == 1)  # a global shutter: the middle instant's, the frame's own
