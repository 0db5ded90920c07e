"""Marine snow's particle field (seasynth.worker.optics.particles): where particles lie, how many there are, their
sizes and their mesh; and the spec's water.particles."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from spec_helpers import refusal

from seasynth.service.camera_model import CameraModel
from seasynth.service.seeds import STREAM_SNOW, frame_rng
from seasynth.service.spec.dataset import parse_spec
from seasynth.service.spec.optics import Port
from seasynth.worker.optics.particles import (
    ICO_FACES,
    ICO_VERTICES,
    MAX_PARTICLES,
    SIZE_BINS,
    VISIBLE,
    bin_expectation,
    cut_depth,
    draw_field,
    frame_field,
    frustum_tans,
    frustum_volume,
    particle_mesh,
    power_law_cdf,
    power_law_quantile,
)
from seasynth.worker.render import View


@st.composite
def views(draw) -> View:
    w = draw(st.integers(16, 400))
    h = draw(st.integers(16, 300))
    fx = draw(st.floats(0.4, 2.0)) * w
    fy = fx * draw(st.floats(0.8, 1.25))
    cx = (w - 1) / 2 + draw(st.floats(-0.2, 0.2)) * w
    cy = (h - 1) / 2 + draw(st.floats(-0.2, 0.2)) * h
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    near = draw(st.floats(0.02, 0.3))
    return View(K=K, width=w, height=h, cam_from_world=np.eye(4), near=near, far=near + draw(st.floats(0.5, 300.0)))


params = st.fixed_dictionaries({
    "density": st.floats(0.0, 3000.0),
    "lo": st.floats(0.1e-3, 2e-3),
    "ratio": st.floats(1.0, 10.0),
    "slope": st.floats(0.0, 6.0),
    "k": st.floats(0.05, 3.0),
})


def _field(view: View, p: dict, seed: int):
    d = (p["lo"], p["lo"] * p["ratio"])
    return draw_field(np.random.default_rng(seed), view, p["density"], d, p["slope"], (0.3, 0.8), p["k"])


def expected_count(view: View, p: dict, nodes: int = 20000) -> float:
    """density x the mean over diameters (power law) of the frustum's volume out to each diameter's cut."""
    u = (np.arange(nodes) + 0.5) / nodes
    d = power_law_quantile(u, p["lo"], p["lo"] * p["ratio"], p["slope"])
    f_px = max(view.K[0, 0], view.K[1, 1])
    z = cut_depth(d, f_px, p["k"], view.far)
    return p["density"] * float(frustum_volume(frustum_tans(view), view.near, z).mean())


@settings(max_examples=60, deadline=None)
@given(view=views(), p=params, seed=st.integers(0, 2**32))
def test_particles_lie_in_the_frustum_within_their_cut_and_size_bounds(view, p, seed):
    assume(expected_count(view, p, 2000) < 20000)
    f = _field(view, p, seed)
    x, y, z = f.centres.T
    t = frustum_tans(view)
    f_px = max(view.K[0, 0], view.K[1, 1])
    assert np.all(z >= view.near) and np.all(z <= cut_depth(f.diameters, f_px, p["k"], view.far) * (1 + 1e-12))
    assert np.all(x >= t[0] * z - 1e-12) and np.all(x <= t[1] * z + 1e-12)
    assert np.all(y >= t[2] * z - 1e-12) and np.all(y <= t[3] * z + 1e-12)
    lo, hi = p["lo"], p["lo"] * p["ratio"]
    assert np.all(f.diameters >= lo * (1 - 1e-9)) and np.all(f.diameters <= hi * (1 + 1e-9))
    assert np.all((f.albedo >= 0.3) & (f.albedo <= 0.8))
    assert f.cut_m[0] <= f.cut_m[1] <= view.far
    # the same generator state draws the same field
    again = _field(view, p, seed)
    assert np.array_equal(again.centres, f.centres) and np.array_equal(again.diameters, f.diameters)


@settings(max_examples=25, deadline=None)
@given(view=views(), p=params)
def test_the_count_is_poisson_with_mean_density_times_the_visible_volume(view, p):
    """Over 40 seeds the total count is Poisson with 40 x the expected count, which is linear in the density."""
    seeds = 40
    assume(expected_count(view, p, 2000) < 2000)
    total = sum(len(_field(view, p, s).diameters) for s in range(seeds))
    lam = seeds * expected_count(view, p)
    assert abs(total - lam) <= 5.0 * math.sqrt(lam) + 1e-3 * lam + 1.0, (total, lam)


@settings(max_examples=8, deadline=None)
@given(density=st.floats(2e4, 1e6), f_px=st.floats(300.0, 3000.0), k=st.floats(0.0, 0.5))
def test_a_field_past_the_particle_budget_raises_its_threshold_until_the_budget_holds(density, f_px, k):
    view = View(K=np.array([[f_px, 0, 159.5], [0, f_px, 119.5], [0, 0, 1]]), width=320, height=240,
                cam_from_world=np.eye(4), near=0.02, far=300.0)
    args = (frustum_tans(view), f_px, power_law_quantile(np.linspace(0, 1, SIZE_BINS + 1), 5e-3, 10e-3, 4.0),
            density, k, view)
    assume(bin_expectation(*args, VISIBLE)[1].sum() > 1.01 * MAX_PARTICLES)
    field = draw_field(np.random.default_rng(0), view, density, (5e-3, 10e-3), 4.0, (0.5, 0.5), k)
    assert field.visible > VISIBLE and field.record((5, 10), 4.0)["visible"] == field.visible
    # the least threshold that keeps the expectation within the budget, and the draw within its Poisson spread
    assert bin_expectation(*args, field.visible)[1].sum() <= MAX_PARTICLES
    assert bin_expectation(*args, field.visible * (1 - 1e-9))[1].sum() > MAX_PARTICLES
    assert len(field.diameters) <= MAX_PARTICLES + 5.0 * math.sqrt(MAX_PARTICLES)
    z = field.centres[:, 2]
    share = math.pi / 4 * (field.diameters * f_px / z) ** 2 * np.exp(-k * z)
    assert np.all(share >= field.visible * (1 - 1e-9))  # every particle drawn is above the threshold used


def test_the_cut_is_where_a_particle_changes_its_pixel_by_the_visible_share():
    d = np.geomspace(1e-4, 1e-2, 50)
    for k in (0.0, 0.05, 0.7, 3.0):
        z = cut_depth(d, 500.0, k, far=1e9)
        share = math.pi / 4 * (d * 500.0 / z) ** 2 * np.exp(-k * z)
        assert np.allclose(share, VISIBLE, rtol=1e-9)
        assert np.all(np.diff(z) > 0)  # larger particles are seen farther
    assert np.all(cut_depth(d, 500.0, 0.1, far=2.0) <= 2.0)


@settings(max_examples=40, deadline=None)
@given(lo=st.floats(1e-4, 1e-2), ratio=st.floats(1.0001, 100.0), slope=st.floats(0.0, 8.0))
def test_power_law_quantile_inverts_its_cdf(lo, ratio, slope):
    u = np.linspace(0.0, 1.0, 101)
    d = power_law_quantile(u, lo, lo * ratio, slope)
    assert np.all(np.diff(d) >= 0) and d[0] == pytest.approx(lo) and d[-1] == pytest.approx(lo * ratio)
    assert np.allclose(power_law_cdf(d, lo, lo * ratio, slope), u, atol=1e-9)


# The least diameter a spec may give is any float > 0 (mm): 5e-324 mm is 0 m, 1e-100 mm makes lo^-3 overflow.
TINY_DIAMETERS = st.one_of(st.sampled_from([0.0, 5e-324, 1e-300, 1e-103]), st.floats(0.0, 1e-3))


@given(lo=TINY_DIAMETERS, hi=st.floats(1e-3, 0.1), slope=st.floats(0.0, 8.0))
def test_power_law_quantile_is_exact_at_its_ends_and_monotone_down_to_a_zero_diameter(lo, hi, slope):
    u = np.linspace(0.0, 1.0, 101)
    d = power_law_quantile(u, lo, hi, slope)
    assert np.all(np.isfinite(d)) and np.all(np.diff(d) >= 0)
    assert d[0] == lo and d[-1] == hi and np.all((d >= lo) & (d <= hi))
    # The round trip holds where the diameters between the bounds resolve it: floats with all their bits (subnormal
    # ones round to a few), and bounds at least 1e-6 apart relatively (one float step is then at most ~2e-10 of the
    # distribution; bounds a few steps apart hold only the few diameters between them).
    if lo > 1e-300 and hi - lo > 1e-6 * hi:
        assert np.allclose(power_law_cdf(d, lo, hi, slope), u, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(view=views(), lo=TINY_DIAMETERS, slope=st.floats(0.0, 8.0), seed=st.integers(0, 2**32 - 1))
def test_a_field_of_vanishing_least_diameter_is_drawn_finite_within_its_bounds(view, lo, slope, seed):
    hi = 2e-3
    f = draw_field(np.random.default_rng(seed), view, 500.0, (lo, hi), slope, (0.3, 0.8), 0.2)
    assert np.all(np.isfinite(f.centres)) and np.all((f.diameters >= lo) & (f.diameters <= hi))
    assert np.all(f.centres[:, 2] >= view.near) and all(math.isfinite(c) for c in f.cut_m)


@settings(max_examples=40, deadline=None)
@given(port=st.one_of(
    st.fixed_dictionaries({"kind": st.just("flat"), "distance_mm": st.floats(1.0, 1000.0),
                           "thickness_mm": st.floats(1.0, 200.0)}),
    st.fixed_dictionaries({"kind": st.just("dome"), "radius_mm": st.floats(30.0, 1000.0),
                           "thickness_mm": st.floats(1.0, 29.0)})),
       big=st.booleans(), seed=st.integers(0, 2**32 - 1))
def test_no_particle_lies_inside_the_housing_of_a_camera_behind_a_port(port, big, seed):
    """The housing holds air: every particle's sphere lies beyond the port's outer surface, and without a port the
    field is draw_field's own."""
    particles = {"enabled": True, "density_per_m3": [3e4, 3e4], "diameter_mm": [1.0, 40.0 if big else 5.0]}
    spec = parse_spec({"seed": seed, "camera": {"width": 32, "height": 24, "port": port},
                       "water": {"jerlov": ["1C"], "particles": particles}})
    view = View(K=np.asarray(spec.camera.K()), width=32, height=24, cam_from_world=np.eye(4), near=0.02, far=20.0)
    water = SimpleNamespace(light=None, water=SimpleNamespace(beta_D=np.array([0.5, 0.5, 0.5])), water_type="1C")
    f = frame_field(spec, 3, water, view)
    model = CameraModel.from_spec(spec.camera)
    assert np.all(model.water_clearance(f.centres) >= f.diameters / 2)
    # The same draws as without a port (draw_field's, from the frame's stream), less those not wholly in the water.
    rng = frame_rng(seed, 3, STREAM_SNOW)
    density = rng.uniform(3e4, 3e4)
    bare = draw_field(rng, view, density, (1e-3, 40e-3 if big else 5e-3), 4.0, (0.4, 0.7), 0.5)
    wet = model.water_clearance(bare.centres) >= bare.diameters / 2
    assert np.array_equal(f.centres, bare.centres[wet]) and np.array_equal(f.diameters, bare.diameters[wet])
    no_port = spec.model_copy(update={"camera": spec.camera.model_copy(update={"port": Port()})})
    assert np.array_equal(frame_field(no_port, 3, water, view).centres, bare.centres)


def test_diameters_follow_the_power_law_where_no_cut_binds():
    """Inside the smallest diameter's cut every size is kept: there the diameters' CDF values are uniform."""
    view = View(K=np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]]), width=160, height=120,
                cam_from_world=np.eye(4), near=0.05, far=100.0)
    lo, hi, slope = 0.5e-3, 5e-3, 4.0
    f = draw_field(np.random.default_rng(3), view, 5e4, (lo, hi), slope, (0.5, 0.5), 0.2)
    inner = f.centres[:, 2] <= f.cut_m[0]
    u = np.sort(power_law_cdf(f.diameters[inner], lo, hi, slope))
    n = len(u)
    assert n > 2000
    ks = np.max(np.abs(u - (np.arange(n) + 0.5) / n))
    assert ks < 1.63 / math.sqrt(n)  # Kolmogorov-Smirnov at the 1% level


def test_the_icosahedron_has_the_sphere_s_area_and_so_its_mean_projected_area():
    tri = ICO_VERTICES[ICO_FACES]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert area == pytest.approx(4 * math.pi, rel=1e-12)
    # Cauchy: the mean over directions of the projected area is a quarter of the surface area
    dirs = np.random.default_rng(0).normal(size=(20000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) / 2
    projected = 0.5 * np.abs(dirs @ normals.T).sum(axis=1)
    assert projected.mean() == pytest.approx(math.pi, rel=0.01)


def test_the_mesh_is_one_icosahedron_per_particle_keyed_by_content():
    view = View(K=np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]), width=64, height=48,
                cam_from_world=np.eye(4), near=0.05, far=50.0)
    f = draw_field(np.random.default_rng(1), view, 3000.0, (1e-3, 4e-3), 3.0, (0.4, 0.7), 0.3)
    m = particle_mesh(f)
    n = len(f.diameters)
    assert m.vertices.shape == (12 * n, 3) and m.faces.shape == (20 * n, 3) and m.faces.max() == 12 * n - 1
    v = m.vertices.reshape(n, 12, 3).astype(np.float64)
    dist = np.linalg.norm(v - f.centres[:, None], axis=2)
    scale = np.linalg.norm(ICO_VERTICES[0])
    assert np.allclose(dist, f.diameters[:, None] / 2 * scale, rtol=0, atol=1e-6)  # float32 vertices
    assert np.allclose(m.albedo.reshape(n, 12, 3), f.albedo[:, None, None], atol=0)
    assert np.all(np.linalg.norm(m.vertices - m.centre, axis=1) <= m.radius + 1e-6)
    assert particle_mesh(f).key == m.key
    g = draw_field(np.random.default_rng(2), view, 3000.0, (1e-3, 4e-3), 3.0, (0.4, 0.7), 0.3)
    assert particle_mesh(g).key != m.key


# --- the spec ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("particles, path, fragment", [
    ({"density_per_m3": [10.0, 1.0]}, "water.particles.density_per_m3", "min 10.0 > max 1.0"),
    ({"density_per_m3": [-1.0, 1.0]}, "water.particles.density_per_m3", "must be >= 0"),
    ({"density_per_m3": [1.0, 1e6]}, "water.particles.density_per_m3", "must lie within [0, 100000.0]"),
    ({"diameter_mm": [0.0, 1.0]}, "water.particles.diameter_mm", "must be > 0"),
    ({"diameter_mm": [2.0, 1.0]}, "water.particles.diameter_mm", "min 2.0 > max 1.0"),
    ({"diameter_mm": [1.0, 101.0]}, "water.particles.diameter_mm", "must lie within [0, 100]"),
    ({"size_slope": -0.5}, "water.particles.size_slope", "greater than or equal to 0"),
    ({"albedo": [0.5, 1.5]}, "water.particles.albedo", "must lie within [0, 1]"),
    ({"enabled": 1}, "water.particles.enabled", "valid boolean"),
    ({"count": 5}, "water.particles.count", "Extra inputs"),
])
def test_bad_particle_fields_are_refused_naming_the_field(particles, path, fragment):
    (line,) = refusal({"water": {"particles": particles}})
    assert line.startswith(f"{path}: ") and fragment in line, line


def test_particles_need_water_and_a_density_where_no_jerlov_type_gives_one():
    (line,) = refusal({"water": {"enabled": False, "particles": {"enabled": True}}})
    assert line.startswith("water: particles: ") and "water.enabled" in line
    explicit = {"absorption": {"min": [0.1] * 3, "max": [0.1] * 3}, "scattering": {"min": [0.1] * 3, "max": [0.1] * 3}}
    for water in ({"jerlov": [], **explicit}, {"model": "physical", **explicit}):
        (line,) = refusal({"water": {**water, "particles": {"enabled": True}}})
        assert line.startswith("water: particles.density_per_m3: "), line
        ok = parse_spec({"water": {**water, "particles": {"enabled": True, "density_per_m3": [5.0, 9.0]}}})
        assert ok.water.particles.density_per_m3 == (5.0, 9.0)
    assert parse_spec({"water": {"particles": {"enabled": True}}}).water.particles.density_per_m3 is None
    assert not parse_spec({}).water.particles.enabled


@given(k=st.sampled_from([0.0, 5e-324, 1e-300, 1e-12, 1e-3]))
def test_the_cut_is_finite_and_continuous_as_the_attenuation_vanishes(k):
    d = np.geomspace(1e-4, 1e-2, 20)
    z = cut_depth(d, 1000.0, k, far=1e9)
    clear = cut_depth(d, 1000.0, 0.0, far=1e9)
    assert np.all(np.isfinite(z)) and np.all(z <= clear)
    if k <= 1e-12:  # attenuation too small to matter: the clear water's cut, to rounding
        assert np.allclose(z, clear, rtol=1e-9)
