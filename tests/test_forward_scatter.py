"""Forward-scatter blur (seasynth.worker.optics.forward_scatter): light kept, nothing spread without scattering,
widths growing with range and b, a spread point's variance the PSF's, the frame's other outputs untouched."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.light import Medium, hg
from seasynth.worker.optics.forward_scatter import (
    SMALL_ANGLE_RAD,
    angular_variance,
    forward_part,
    forward_scatter,
    phase_split,
    spread,
)

coefficient = st.floats(0.0, 3.0)
rgb = st.tuples(coefficient, coefficient, coefficient).map(np.array)
phase_g = st.floats(0.0, 0.99)
seeds = st.integers(0, 2**32 - 1)
sizes = st.tuples(st.integers(8, 64), st.integers(8, 48))


def medium(a, b, g) -> Medium:
    return Medium(a=np.asarray(a, float), b=np.asarray(b, float), g=g, surface_z=10.0)


def frame(seed: int, w: int, h: int, far: float = 20.0):
    """A random clean image, range (some +inf) and the image the physical model forms from them plus some path
    radiance, for a medium."""
    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.0, 1.0, (h, w, 3)).astype(np.float32)
    range_m = rng.uniform(0.0, far, (h, w)).astype(np.float32)
    range_m[rng.uniform(size=(h, w)) < 0.1] = np.inf
    return clean, range_m, rng


@settings(max_examples=60, deadline=None)
@given(seeds, sizes, rgb, rgb, phase_g, st.floats(50.0, 800.0), st.floats(0.5, 2.0))
def test_the_blur_moves_light_and_keeps_all_of_it(seed, size, a, b, g, fx, aspect):
    clean, range_m, rng = frame(seed, *size)
    m = medium(a, b, g)
    image = (clean * np.exp(-m.k * np.where(np.isfinite(range_m), range_m, 1e9)[..., None])).astype(np.float32)
    image += rng.uniform(0.0, 0.2, image.shape).astype(np.float32)  # path radiance, left alone
    out, _ = forward_scatter(image, clean, range_m, m, fx, fx * aspect)
    scale = float(image.sum(axis=(0, 1)).max())
    np.testing.assert_allclose(out.sum(axis=(0, 1)), image.sum(axis=(0, 1)), rtol=0, atol=2e-5 * scale + 1e-6)
    part = forward_part(clean, range_m, m)
    # What is not scattered (the sharp part and the path radiance) stays where it was: the change is the
    # scattered part's spread minus itself.
    assert np.all(out - (image - part) >= -1e-5 * scale)


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 1.0), sizes, st.floats(0.0, 5e3), st.floats(0.5, 2.0))
def test_a_uniform_image_under_one_kernel_is_unchanged(level, size, var, aspect):
    w, h = size
    light = np.full((h, w, 3), level, np.float32)
    out, _ = spread(light, np.full((h, w, 3), var), aspect)
    np.testing.assert_allclose(out, light, rtol=0, atol=2e-6)


@settings(max_examples=40, deadline=None)
@given(seeds, sizes, rgb, phase_g)
def test_no_scattering_or_no_range_changes_no_byte(seed, size, a, g):
    clean, range_m, _ = frame(seed, *size)
    image = np.random.default_rng(seed + 1).uniform(0.0, 1.0, clean.shape).astype(np.float32)
    unscattered = forward_scatter(image, clean, range_m, medium(a, np.zeros(3), g), 300.0, 300.0)[0]
    at_the_lens = forward_scatter(image, clean, np.zeros_like(range_m), medium(a, a + 0.5, g), 300.0, 300.0)[0]
    assert unscattered.tobytes() == image.tobytes()
    assert at_the_lens.tobytes() == image.tobytes()


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 5.0), phase_g, st.lists(st.floats(0.0, 100.0), min_size=2, max_size=8))
def test_the_kernel_widens_with_range_and_with_b(b, g, ranges):
    r = np.sort(np.asarray(ranges))
    by_range = angular_variance(np.full(3, b), g, r[None, :])[0, :, 0]
    assert np.all(np.diff(by_range) >= -1e-12 * by_range[-1])
    by_b = angular_variance(r / 20.0, g, np.full((1, 1), 5.0))[0, 0]
    assert np.all(np.diff(by_b) >= -1e-12 * by_b[-1])
    # One turn's worth at the lens; every turn adds as much.
    one = phase_split(g)[0] * phase_split(g)[1] / 6
    np.testing.assert_allclose(angular_variance(np.full(3, b), g, np.zeros((1, 1)))[0, 0], one, rtol=1e-12)
    assert np.all(by_range >= one * (1 - 1e-12)) and np.all(by_range <= one * (1 + b * r) * (1 + 1e-12))


@settings(max_examples=30, deadline=None)
@given(phase_g)
def test_the_small_angle_part_is_the_phase_functions(g):
    share, mean_square = phase_split(g)
    theta = np.linspace(0.0, SMALL_ANGLE_RAD, 20001)
    weight = hg(np.cos(theta), g) * 2 * np.pi * np.sin(theta)  # HG integrates to 1 over the sphere
    np.testing.assert_allclose(share, np.trapezoid(weight, theta), rtol=1e-4)
    np.testing.assert_allclose(mean_square, np.trapezoid(weight * theta**2, theta) / share, rtol=1e-4)
    assert 0 < mean_square < SMALL_ANGLE_RAD**2


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, 60.0), st.floats(0.7, 1.4))
def test_a_point_spreads_with_its_kernels_variance(var, aspect):
    """A lit pixel far from the edges spreads to its variance along x and aspect^2 times it along y, centred."""
    h = w = 129
    light = np.zeros((h, w, 3), np.float32)
    light[64, 64] = 1.0
    out, _ = spread(light, np.full((h, w, 3), var), aspect)
    y, x = np.mgrid[:h, :w] - 64
    p = out[..., 0].astype(np.float64)
    np.testing.assert_allclose([(p * x).sum(), (p * y).sum()], 0.0, atol=1e-4)
    np.testing.assert_allclose((p * x**2).sum(), var, rtol=0.02, atol=0.02)
    np.testing.assert_allclose((p * y**2).sum(), var * aspect**2, rtol=0.02, atol=0.02)


@settings(max_examples=10, deadline=None)
@given(seeds, sizes, rgb, rgb, phase_g)
def test_the_blur_is_a_function_of_its_inputs(seed, size, a, b, g):
    clean, range_m, _ = frame(seed, *size)
    image = clean * 0.5
    m = medium(a, b, g)
    first = forward_scatter(image, clean, range_m, m, 200.0, 210.0)[0]
    assert first.tobytes() == forward_scatter(image, clean.copy(), range_m.copy(), m, 200.0, 210.0)[0].tobytes()


def test_a_frame_with_the_blur_changes_its_image_alone(render_session):
    base = {"camera.width": 96, "camera.height": 72, "outputs.depth": True, "outputs.instance": True,
            "water.jerlov": ["3C"], "water.model": "physical"}
    off = render_session.frame_files(load_spec("examples/urchins.yaml", base), 1)
    on = render_session.frame_files(load_spec("examples/urchins.yaml", {**base, "water.forward_scatter": True}), 1)
    assert on.keys() == off.keys()
    changed = {k for k in on if on[k] != off[k]}
    assert {k.split("/")[0] for k in changed} == {"image_2", "meta"}
    meta_on = json.loads(next(on[k] for k in on if k.startswith("meta")))
    meta_off = json.loads(next(off[k] for k in off if k.startswith("meta")))
    assert meta_on["optics"]["forward_scatter"]["levels_px"]
    assert "optics" not in meta_off
    assert {k: v for k, v in meta_on.items() if k not in ("optics", "spec", "spec_sha256")} == \
        {k: v for k, v in meta_off.items() if k not in ("optics", "spec", "spec_sha256")}
