"""The sensor (seasynth.worker.optics.sensor): exposure, gain, photon and read noise, white balance; the lens and
sensor spec fields' refusals; every optical effect seeded (the same bytes from another process)."""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from spec_helpers import refusal

from seasynth.service.seeds import STREAM_NOISE, STREAM_SENSOR, frame_rng
from seasynth.service.spec.dataset import load_spec, parse_spec
from seasynth.worker.optics.base import Shot
from seasynth.worker.optics.sensor import Sensor, gray_world, metered_scale, photon_read_noise
from seasynth.worker.render import RenderResult

# Statistical tests fail by chance with probability under 1e-6 per case: 5 standard deviations of the estimate.
Z = 5.0
seeds = st.integers(0, 2**32 - 1)


def develop(noise: dict, image: np.ndarray, seed: int = 0, index: int = 0) -> tuple[np.ndarray, dict]:
    spec = parse_spec({"seed": seed, "noise": noise})
    shot = Shot(spec=spec, index=index, scene=None, view=None, render_view=None, items=[])
    out = Sensor().develop(shot, RenderResult(image=image, clean=None, instance=None, range_m=None))
    return out.image, shot.record


@settings(max_examples=40, deadline=None)
@given(full_well=st.floats(100, 1e5), gain=st.floats(0.25, 16), signal=st.floats(1e-3, 1), seed=seeds)
def test_photon_noise_variance_is_proportional_to_the_signal(full_well, gain, signal, seed):
    per_unit = full_well / gain
    if signal * per_unit < 1:  # fewer than one electron on average: the statement holds, but the bound is loose
        signal = 1 / per_unit
    image = np.full((100, 100, 3), signal, np.float32)
    out = photon_read_noise(image, full_well, 0.0, gain, frame_rng(seed, 0, STREAM_SENSOR)).astype(np.float64)
    n, lam = out.size, signal * per_unit
    expected = signal * gain / full_well  # var = lambda / per_unit^2
    # Poisson: the sample variance's relative standard deviation is sqrt((1 / lambda + 2) / n); the mean's sqrt(1/(n lambda)).
    assert abs(out.var(ddof=1) / expected - 1) < Z * math.sqrt((1 / lam + 2) / n)
    assert abs(out.mean() / signal - 1) < Z / math.sqrt(n * lam)


@settings(max_examples=30, deadline=None)
@given(full_well=st.floats(100, 1e5), gain=st.floats(0.25, 16), read=st.floats(0.5, 50), seed=seeds)
def test_read_noise_at_zero_signal_is_gaussian_of_its_sigma(full_well, gain, read, seed):
    out = photon_read_noise(np.zeros((100, 100, 3), np.float32), full_well, read, gain,
                            frame_rng(seed, 0, STREAM_SENSOR)).astype(np.float64)
    sigma = read * gain / full_well
    n = out.size
    assert abs(out.var(ddof=1) / sigma**2 - 1) < Z * math.sqrt(2 / (n - 1))
    assert abs(out.mean()) < Z * sigma / math.sqrt(n)


@settings(max_examples=60, deadline=None)
@given(target=st.floats(0.01, 0.95), scale=st.floats(1e-3, 100), dark=st.floats(0, 0.5), seed=seeds)
def test_auto_exposure_reaches_its_target(target, scale, dark, seed):
    rng = np.random.default_rng(seed)
    image = (rng.lognormal(0, 1, (24, 32, 3)) * scale).astype(np.float32)
    image[rng.uniform(size=(24, 32)) < dark] = 0  # black pixels: the target may be out of reach
    out, record = develop({"auto_exposure": target, "gain": 2.0}, image)
    reachable = target < np.mean(image > 0)
    if reachable:
        assert abs(out.astype(np.float64).mean() - target) < 1e-5
    else:
        assert np.all(out[image > 0] == 1.0)
    assert record["sensor"]["gain"] == 2.0 and "noise" not in record
    s = metered_scale(image.astype(np.float64), target)
    if reachable:
        assert abs(np.clip(s * image.astype(np.float64), 0, 1).mean() - target) < 1e-9


@settings(max_examples=30, deadline=None)
@given(ev=st.floats(-4, 4), gain=st.floats(0.5, 4), wb=st.tuples(*[st.floats(0.2, 5)] * 3), seed=seeds)
def test_fixed_exposure_gain_and_white_balance_without_noise_are_products_then_a_clip(ev, gain, wb, seed):
    image = np.random.default_rng(seed).uniform(0, 0.5, (12, 16, 3)).astype(np.float32)
    out, record = develop({"exposure_ev": ev, "gain": gain, "white_balance": list(wb)}, image)
    np.testing.assert_allclose(out, np.clip(image * 2**ev * gain * np.array(wb), 0, 1), rtol=1e-5, atol=1e-7)
    assert record["sensor"]["white_balance"] == list(wb)


@settings(max_examples=30, deadline=None)
@given(tint=st.tuples(*[st.floats(0.05, 1)] * 3), seed=seeds)
def test_gray_world_makes_the_channel_means_equal(tint, seed):
    image = (np.random.default_rng(seed).uniform(0, 0.3, (12, 16, 3)) * np.array(tint)).astype(np.float32)
    m = gray_world(image)
    means = (image * m).reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(means, means.mean(), rtol=1e-5)
    np.testing.assert_allclose(means.mean(), image.mean(), rtol=1e-5)  # their mean kept


@settings(max_examples=20, deadline=None)
@given(sigma=st.floats(1e-4, 0.5), seed=st.integers(0, 2**31), index=st.integers(0, 1000))
def test_gaussian_sigma_alone_is_what_it_was(sigma, seed, index):
    image = np.random.default_rng(index).uniform(0, 1, (12, 16, 3)).astype(np.float32)
    out, record = develop({"gaussian_sigma": sigma}, image, seed, index)
    rng = frame_rng(seed, index, STREAM_NOISE)
    assert out.tobytes() == (image + rng.normal(0.0, sigma, image.shape).astype(np.float32)).tobytes()
    assert record == {"noise": {"gaussian_sigma_linear": sigma}}


def at_the_bounds(lo: float, hi: float):
    """Floats in [lo, hi], its ends and the least float above 0 drawn often."""
    return st.one_of(st.sampled_from([lo, hi]), st.floats(lo, hi))


@settings(max_examples=150, deadline=None)
@given(noise=st.fixed_dictionaries({}, optional={
    "gaussian_sigma": at_the_bounds(0.0, 0.5), "full_well_e": at_the_bounds(1.0, 1e7),
    "gain": at_the_bounds(5e-324, 1000.0), "auto_exposure": at_the_bounds(5e-324, 0.9999999),
    "white_balance": st.one_of(st.just("gray_world"), st.lists(at_the_bounds(5e-324, 100.0), min_size=3,
                                                                max_size=3))}),
    read=at_the_bounds(0.0, 1e4), level=st.sampled_from([0.0, 1e-40, 1e-3, 1.0, 1e12]), dark=st.booleans(),
    seed=seeds)
def test_any_sensor_at_its_bounds_records_finite_values_in_range(noise, read, level, dark, seed):
    """Gains, white balances and exposure targets down to 5e-324 and light from 1e-40 to 1e12 (the spec's caps):
    the recorded image is finite and within [0, 1], and meta's record is finite."""
    if "full_well_e" in noise:
        noise["read_noise_e"] = read
    image = (np.random.default_rng(seed).random((6, 8, 3)) * level).astype(np.float32)
    if dark:
        image[..., 1] = 0.0
    out, record = develop(noise, image, seed)
    assert out.dtype == np.float32 and np.all(np.isfinite(out))
    if parse_spec({"noise": noise}).noise.sensor_on:
        assert out.min() >= 0.0 and out.max() <= 1.0
    json.dumps(record, allow_nan=False)


MEMBERS = ("tuple[constrained-float, constrained-float, constrained-float].1", "literal['gray_world']")
REFUSED = [
    ({"noise": {"read_noise_e": 3.0}}, "noise", "read_noise_e is in electrons: give full_well_e too"),
    ({"noise": {"exposure_ev": 1.0, "auto_exposure": 0.2}}, "noise", "either exposure_ev or auto_exposure"),
    ({"noise": {"auto_exposure": 1.0}}, "noise.auto_exposure", "less than 1"),
    ({"noise": {"white_balance": [1.0, 0.0, 1.0]}}, "noise.white_balance", "greater than 0"),
    ({"noise": {"white_balance": "auto"}}, "noise.white_balance", "gray_world"),
    ({"camera": {"aperture_f": 0.1}}, "camera.aperture_f", "greater than or equal to 0.5"),
    ({"camera": {"aperture_f": 2.0, "focus_m": 0.05, "hfov_deg": 2.0, "sensor_width_mm": 100.0}}, "camera",
     "focus_m 0.05 m is at or inside the focal length"),
    ({"camera": {"exposure_s": -0.01}}, "camera.exposure_s", "greater than or equal to 0"),
    ({"camera": {"velocity_m_s": [2.0, 1.0]}}, "camera.velocity_m_s", "min 2.0 > max 1.0"),
    ({"camera": {"vignetting": -1.0}}, "camera.vignetting", "greater than or equal to 0"),
]


@pytest.mark.parametrize(("data", "field", "message"), REFUSED, ids=[r[1] + ":" + r[2][:20] for r in REFUSED])
def test_lens_and_sensor_refusals_name_the_field(data, field, message):
    lines = refusal(data)
    # A union's errors name the field and then the member that refused (noise.white_balance.tuple[...].1).
    assert any(line.split(":")[0] in (field, *(f"{field}.{m}" for m in MEMBERS)) and message in line
               for line in lines), lines


ALL_ON = {"camera.width": 48, "camera.height": 36, "outputs.meta": True, "outputs.instance": True,
          "camera.aperture_f": 1.0, "camera.focus_m": 0.4, "camera.sensor_width_mm": 60.0, "camera.vignetting": 1.5,
          "camera.exposure_s": 0.01, "camera.readout_s": 0.01, "camera.velocity_m_s": [0.5, 1.0],
          "camera.angular_rate_deg_s": [5.0, 10.0], "noise.full_well_e": 3000.0, "noise.read_noise_e": 4.0,
          "noise.gain": 2.0, "noise.auto_exposure": 0.25, "noise.white_balance": "gray_world",
          "noise.gaussian_sigma": 0.01}
DIGEST = """
import hashlib, json, sys
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession
with RenderSession() as s:
    files = s.frame_files(load_spec("examples/urchins.yaml", json.loads(sys.argv[1])), 5)
print(json.dumps({k: hashlib.sha256(v).hexdigest() for k, v in sorted(files.items())}))
"""


def test_every_effect_on_is_the_same_bytes_in_another_process(render_session):
    files = render_session.frame_files(load_spec("examples/urchins.yaml", ALL_ON), 5)
    here = {k: hashlib.sha256(v).hexdigest() for k, v in sorted(files.items())}
    out = subprocess.run([sys.executable, "-c", DIGEST, json.dumps(ALL_ON)], capture_output=True, text=True,
                         check=True, env=os.environ)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == here
    optics = json.loads(files["meta/000005.json"])["optics"]
    assert set(optics) == {"depth_of_field", "motion_blur", "vignetting", "sensor"}
