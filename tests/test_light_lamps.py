"""Tests of a lamp's light on its way out (`seasynth.worker.light.lamps.light_factor`): the unscattered beam keeps the spot's
sharp profile, the forward-scattered rest spreads in angle with the distance and the water's scattering, and no
power is made or lost by the spreading."""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from seasynth.worker.light import Lamp, Medium
from seasynth.worker.light.lamps import (
    SPREAD_DISTANCE_M,
    SPREAD_MIN_SHARE,
    cone_energy,
    cone_interval,
    light_factor,
    profile,
    reach,
)

TURBID = Medium(a=np.array([0.3, 0.08, 0.13]), b=np.array([0.857, 1.10, 1.43]), g=0.92, surface_z=0.0)  # Jerlov 3C
CLEAR = Medium(a=np.array([0.3, 0.1, 0.05]), b=np.array([0.006, 0.002, 0.001]), g=0.85, surface_z=0.0)


def lamp(beam_deg=20.0, cutoff_deg=35.0) -> Lamp:
    return Lamp(position_cam=np.zeros(3), direction_cam=np.array([0.0, 0.0, 1.0]), cutoff_rad=math.radians(cutoff_deg),
                beam_rad=math.radians(beam_deg), intensity=np.ones(3))


def factor(lp, theta, d, m=TURBID):
    return light_factor(lp, np.cos(np.asarray(theta, dtype=np.float64)), np.full(np.shape(theta), d), m.c, m.k, m.b,
                        m.g)


@pytest.mark.parametrize("d", [0.01, 0.5, 2.0, 5.0, 20.0, 200.0])
@pytest.mark.parametrize("cone", [(20.0, 35.0), (1.0, 2.0), (35.0, 35.0), (60.0, 89.0)])
def test_spreading_keeps_the_power_the_water_leaves_in_the_light_field(d, cone):
    """Over the whole sphere the lamp's light is its profile's solid angle times exp(-K d): the unscattered beam
    exp(-c d) plus the forward-scattered rest, however far it has spread (up to backwards, past 90 degrees)."""
    lp = lamp(*cone)
    for ch in range(3):
        f = lambda th: float(factor(lp, np.array([th]), d)[0, ch]) * math.sin(th)  # noqa: E731
        kinks = sorted({lp.beam_rad, lp.cutoff_rad})
        total = sum(quad(f, lo, hi, limit=400, epsabs=0, epsrel=1e-11)[0]
                    for lo, hi in zip([0.0, *kinks], [*kinks, math.pi]))
        expected = cone_energy(lp) * math.exp(-TURBID.k[ch] * d)
        assert total == pytest.approx(expected, rel=1e-6)


def test_cone_energy_is_the_profiles_solid_angle_over_two_pi():
    for beam, cut in [(20.0, 35.0), (0.5, 0.6), (89.0, 89.5), (10.0, 10.0)]:
        lp = lamp(beam, cut)
        kinks = sorted({lp.beam_rad, lp.cutoff_rad})
        exact = sum(quad(lambda th: float(profile(lp, np.cos(th))) * math.sin(th), lo, hi, epsrel=1e-12)[0]
                    for lo, hi in zip([0.0, *kinks], [*kinks, math.pi]))
        assert cone_energy(lp) == pytest.approx(exact, rel=1e-9)


def test_without_forward_scattering_kept_the_light_is_the_sharp_beam_exactly():
    """K = c (scattering far below absorption, or none): nothing spreads; the spot's profile times exp(-c d)."""
    assert np.array_equal(CLEAR.k, CLEAR.c)
    lp, theta = lamp(), np.radians(np.linspace(0.0, 180.0, 361))
    for d in (0.3, 3.0, 30.0):
        expected = profile(lp, np.cos(theta))[:, None] * np.exp(-CLEAR.c * d)
        np.testing.assert_array_equal(factor(lp, theta, d, CLEAR), expected)
        assert np.all(factor(lp, np.radians([35.0, 60.0, 120.0]), d, CLEAR) == 0.0)


def test_turbid_water_glows_past_the_cutoff_more_with_distance_while_the_beams_core_empties():
    """Relative to exp(-K d), the light on the axis falls with distance (spread out of the core); past the 35 degree
    cutoff it rises from nothing: at 70 degrees once the spread reaches it, then steadily, at 45 degrees to a peak (beyond it the light has spread
    wider still); the profile falls with angle at every distance."""
    lp = lamp()
    ds = np.array([0.05, 0.5, 1.0, 2.0, 4.0, 8.0])
    rel = np.stack([factor(lp, np.radians([0.0, 45.0, 70.0]), d) / np.exp(-TURBID.k * d) for d in ds])
    assert np.all(np.diff(rel[:, 0], axis=0) < 0)
    assert np.all(np.diff(rel[:, 2], axis=0) >= 0) and np.all(rel[0, 2] == 0) and np.all(rel[-1, 2] > 0.004)
    assert np.all(rel[0, 1] < 2e-3) and np.all(rel[:, 1].max(axis=0) > 0.15)
    for d in ds:
        f = factor(lp, np.radians(np.linspace(0.0, 180.0, 181)), d)
        assert np.all(np.diff(f, axis=0) <= 0)


def test_bluer_channels_that_scatter_more_spread_more():
    lp = lamp()
    rel = factor(lp, np.radians([0.0, 50.0]), 3.0) / np.exp(-TURBID.k * 3.0)
    assert np.all(np.diff(rel[1]) > 0)  # b rises from red to blue: more light past the cutoff
    assert np.all(np.diff(rel[0]) < 0)  # and less left on the axis


@pytest.mark.parametrize("m", [TURBID, CLEAR, Medium(a=np.full(3, 1e-9), b=np.full(3, 1e5), g=0.99, surface_z=0.0),
                               Medium(a=np.zeros(3), b=np.zeros(3), g=0.0, surface_z=0.0)],
                         ids=["turbid", "clear", "scattering-1e5", "vacuum"])
def test_finite_and_non_negative_from_a_millimetre_to_a_megametre(m):
    lp = lamp(1.0, 2.0)
    theta = np.radians(np.linspace(0.0, 180.0, 91))
    with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):
        for d in (1e-3, 1.0, 1e3, 1e6):
            f = factor(lp, theta, d, m)
            assert np.all(np.isfinite(f)) and np.all(f >= 0)


def test_the_cone_interval_is_where_sampled_points_lie_inside_the_cone():
    """Random rays, apexes, axes and half angles (1-89 degrees): every point of [0, t_end] strictly inside the
    returned interval is in the cone and every point outside it is not, sampled at 2,001 points per ray."""
    rng = np.random.default_rng(7)
    n = 400
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = np.linspace(0.0, 1.0, 2001)
    for _ in range(5):
        apex = rng.normal(size=3) * rng.choice([0.0, 0.1, 1.0, 5.0])
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        half = np.full(n, math.radians(rng.uniform(1.0, 89.0)))
        t_end = rng.uniform(0.1, 20.0, size=n)
        t0, t1 = cone_interval(dirs, apex, axis, half, t_end)
        assert np.all(0 <= t0) and np.all(t0 <= t1) and np.all(t1 <= t_end)
        ts = t[None, :] * t_end[:, None]
        v = dirs[:, None, :] * ts[..., None] - apex
        cos = (v @ axis) / np.maximum(np.linalg.norm(v, axis=-1), 1e-300)
        inside = cos > np.cos(half[:, None])
        margin = 1e-9 * t_end[:, None]
        strictly_in = (ts > t0[:, None] + margin) & (ts < t1[:, None] - margin)
        strictly_out = (ts < t0[:, None] - margin) | (ts > t1[:, None] + margin)
        edge = np.abs(cos - np.cos(half[:, None])) < 1e-9
        assert np.all(inside[strictly_in] | edge[strictly_in])
        assert not np.any(inside[strictly_out] & ~edge[strictly_out])


def test_a_cone_of_ninety_degrees_or_more_keeps_the_whole_ray():
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    t0, t1 = cone_interval(dirs, np.zeros(3), np.array([0.0, 0.0, 1.0]), np.full(2, math.pi / 2), np.full(2, 3.0))
    np.testing.assert_array_equal(t0, [0.0, 0.0])
    np.testing.assert_array_equal(t1, [3.0, 3.0])


def test_reach_bounds_where_the_light_is_not_zero():
    """light_factor is exactly 0 past `reach` at every distance up to d_max, and the channel that spreads most (the
    largest b) is lit just within it."""
    for m in (TURBID, CLEAR):
        lp = lamp()
        for d_max in (0.1, 1.0, 10.0):
            edge = float(reach(lp, m.c, m.k, m.b, m.g, d_max))
            ds = np.linspace(1e-3, d_max, 50)
            past = np.linspace(edge, math.pi, 50)
            assert all(np.all(factor(lp, past, d, m) == 0) for d in ds)
            assert edge < math.pi and factor(lp, np.array([edge - 0.02]), d_max, m)[0, np.argmax(m.b)] > 0


def test_a_frame_spreads_lamp_light_only_where_the_water_keeps_forward_scattered_light():
    """Terms.lamp_spread (and the shader's LAMP_SPREAD) is on with lamps in turbid water, off without lamps, in water
    that keeps no forward-scattered light (K = c) and in clear ocean water, where what it would move is under
    SPREAD_MIN_SHARE: a term a frame does not need costs nothing."""
    from seasynth.service.spec.dataset import DatasetSpec
    from seasynth.worker.light.build import sample_physical
    from seasynth.worker.render import Lighting

    lamps = [{"offset_m": [0.3, 0.0, 0.0], "direction": [0.0, 0.0, 1.0], "intensity": [2.0, 2.0]}]
    cases = [({"jerlov": ["3C"]}, lamps, True), ({"jerlov": ["3C"]}, [], False),
             ({"absorption": {"min": [0.3, 0.1, 0.05], "max": [0.3, 0.1, 0.05]},
               "scattering": {"min": [0.003, 0.001, 0.0005], "max": [0.003, 0.001, 0.0005]}}, lamps, False),
             ({"jerlov": ["I"]}, lamps, False), ({"jerlov": ["II"]}, lamps, True)]
    for water, lamp_specs, on in cases:
        spec = DatasetSpec.model_validate({"water": {"model": "physical", **water},
                                           "lighting": {"lamps": lamp_specs, "sun_elevation_deg": [-10.0, -5.0]}})
        light, _ = sample_physical(spec, np.random.default_rng(1), Lighting(np.array([0.0, 0.0, -1.0]), 0.0, 0.0),
                                   top_z=0.0)
        assert light.terms.lamp_spread is on and ("lamp_spread" in light.terms.names()) is on
        m = light.medium
        assert bool(np.any(m.k < m.c)) is ("jerlov" in water)  # Jerlov I keeps a little: below the threshold
        share = -np.expm1(-(m.c - m.k) * SPREAD_DISTANCE_M)
        assert bool(share.max() >= SPREAD_MIN_SHARE) is (on or not lamp_specs)
