"""The water column's solved light field (worker/light/column.py) against conservation laws and exact limits."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from seasynth.worker.light import SNELL_CONE_DEG, hg
from seasynth.worker.light.column import directions, path_radiance, solve, to_sun_frame

SETTINGS = settings(max_examples=6, deadline=None, derandomize=True, phases=(Phase.explicit, Phase.generate))


@SETTINGS
@given(a=st.floats(0.05, 1.0), albedo=st.floats(0.2, 0.95), g=st.floats(0.0, 0.95), mu_sun=st.floats(0.66, 1.0),
       sky_share=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_gershun_net_irradiance_falls_by_absorbed_scalar_irradiance(a, albedo, g, mu_sun, sky_share, seed):
    """E(0) - E(z) = a * integral_0^z E_0: the net downward flux at the surface (what entered less what left through
    it, a surface-crossing estimate) minus the net flux at depth (collision estimates) is what was absorbed above."""
    b = a * albedo / (1.0 - albedo)
    c = a + b
    col = solve(a, b, g, mu_sun, 1.0 - sky_share, sky_share, 6.0 / a, np.random.default_rng(seed), photons=6000)
    sky_flux = math.pi * sky_share * math.sin(math.radians(SNELL_CONE_DEG)) ** 2
    entered = (1.0 - sky_share) * mu_sun + sky_flux
    net_top = entered - col.escaped
    absorbed = a * col.dz * (np.cumsum(col.e_0) - 0.5 * col.e_0)  # to each layer's centre
    m = col.z < 3.0 / c + 1.0 / a  # where the column still carries a tenth or more of the light
    error = (col.e_d - col.e_u)[m] - (net_top - absorbed[m])
    assert np.abs(error).max() < 0.06 * entered
    assert (col.e_d >= 0).all() and (col.e_u >= 0).all() and (col.e_0 >= col.e_d + col.e_u - 1e-12).all()
    assert (col.j >= 0).all()


def single_scattering(b, c, g, mu_sun, e_sun, sky, v, depth):
    """(n,) b x the exact single scattering of the refracted sun and the window's sky along views v (n, 3) (sun
    frame) from a camera at `depth` in water of attenuation c, by quadrature (independent of the solver)."""
    s = np.array([math.sqrt(1.0 - mu_sun**2), 0.0, mu_sun])
    wz = v[:, 2]
    # Along t: depth(t) = depth - t wz, the sun's light exp(-c depth(t) / mu_sun) exp(-c t).
    rate = c - c * wz / mu_sun
    t_end = np.where(wz > 0, depth / np.where(wz > 0, wz, 1.0), np.inf)
    with np.errstate(over="ignore", invalid="ignore"):
        path = np.where(np.isfinite(t_end), -np.expm1(-rate * np.where(np.isfinite(t_end), t_end, 0.0)) / rate,
                        1.0 / rate)
    sun = e_sun * hg(v @ s, g) * np.exp(-c * depth / mu_sun) * path
    x, wx = np.polynomial.legendre.leggauss(48)
    cos_c = math.cos(math.radians(SNELL_CONE_DEG))
    mu = cos_c + (1.0 - cos_c) * (x + 1.0) / 2.0
    phi = (np.arange(96) + 0.5) * (2.0 * math.pi / 96)
    frm = directions(np.arccos(mu)[:, None], phi[None, :]).reshape(-1, 3)
    weight = np.repeat(wx * (1.0 - cos_c) / 2.0, 96) * (2.0 * math.pi / 96)
    rate_sky = c - c * wz[:, None] / mu[None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        path_sky = np.where(np.isfinite(t_end)[:, None], -np.expm1(-rate_sky * np.where(
            np.isfinite(t_end), t_end, 0.0)[:, None]) / rate_sky, 1.0 / rate_sky)
    per = np.exp(-c * depth / mu)[None, :] * path_sky  # (n, mu)
    sky_part = sky * ((hg(v @ frm.T, g) * weight[None, :]).reshape(len(v), 48, 96).sum(axis=2) * per).sum(axis=1)
    return b * (sun + sky_part)


@SETTINGS
@given(a=st.floats(0.05, 1.0), g=st.floats(0.0, 0.95), mu_sun=st.floats(0.66, 1.0), depth=st.floats(0.5, 20.0),
       seed=st.integers(0, 2**32 - 1))
def test_weak_scattering_gives_the_single_scattering_of_sun_and_sky(a, g, mu_sun, depth, seed):
    """b -> 0: the path radiance is b times the exact single scattering of the sun's beam and the window's sky."""
    b = 1e-4 * a
    rng = np.random.default_rng(seed)
    col = solve(a, b, g, mu_sun, 1.0, 0.5, depth + 12.0 / a, rng, photons=4000)
    v = directions(np.arccos(rng.uniform(-1.0, 1.0, 64)), rng.uniform(-math.pi, math.pi, 64))
    want = single_scattering(b, a + b, g, mu_sun, 1.0, 0.5, v, depth)
    got = path_radiance(col, v, depth)
    np.testing.assert_allclose(got, want, rtol=0.01)


def isotropic_k(omega: float) -> float:
    """The asymptotic diffuse attenuation (per unit c) of isotropically scattering water of albedo omega: the root k
    in (0, 1) of omega / (2 k) ln((1 + k) / (1 - k)) = 1, by bisection."""
    lo, hi = 1e-9, 1.0 - 1e-15
    for _ in range(200):
        k = 0.5 * (lo + hi)
        if omega / (2.0 * k) * math.log((1.0 + k) / (1.0 - k)) > 1.0:
            hi = k
        else:
            lo = k
    return 0.5 * (lo + hi)


@SETTINGS
@given(omega=st.floats(0.85, 0.97), c=st.floats(0.2, 2.0), mu_sun=st.floats(0.66, 1.0),
       sky_share=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_deep_downwelling_decays_at_the_asymptotic_attenuation(omega, c, mu_sun, sky_share, seed):
    """Isotropic scattering: deep down E_d falls exponentially at the exact asymptotic K (the transport equation's
    eigenvalue), whatever lit the surface. (Albedos from 0.85: below, the beam's transient still dominates at these
    depths, and the weight window keeps too few photons there for a 6% slope.)"""
    col = solve(c * (1.0 - omega), c * omega, 0.0, mu_sun, 1.0 - sky_share, sky_share, 24.0 / c,
                np.random.default_rng(seed), photons=8000)
    m = (col.z * c >= 6.0) & (col.z * c <= 14.0)  # optical depths past the beam's transient, short of the column's end
    k = -np.polyfit(col.z[m] * c, np.log(col.e_d[m]), 1)[0]
    assert abs(k / isotropic_k(omega) - 1.0) < 0.04


@SETTINGS
@given(g=st.floats(0.0, 0.95), sun_azimuth=st.floats(-math.pi, math.pi), depth=st.floats(0.5, 10.0),
       seed=st.integers(0, 2**32 - 1))
def test_path_radiance_is_mirror_symmetric_about_the_suns_plane(g, sun_azimuth, depth, seed):
    """Views mirrored in the sun's vertical plane see the same, non-negative, path radiance."""
    rng = np.random.default_rng(seed)
    col = solve(0.2, 0.5, g, 0.9, 1.0, 0.3, depth + 20.0, rng, photons=4000)
    sun = directions(math.acos(0.9), sun_azimuth)
    v = directions(np.arccos(rng.uniform(-1.0, 1.0, 32)), rng.uniform(-math.pi, math.pi, 32))
    normal = np.array([-math.sin(sun_azimuth), math.cos(sun_azimuth), 0.0])  # of the sun's vertical plane
    mirrored = v - 2.0 * (v @ normal)[:, None] * normal
    lv = path_radiance(col, to_sun_frame(v, sun), depth)
    lm = path_radiance(col, to_sun_frame(mirrored, sun), depth)
    np.testing.assert_allclose(lv, lm, rtol=1e-9)
    assert (lv > 0).all()


@SETTINGS
@given(a=st.floats(0.1, 0.5), albedo=st.floats(0.5, 0.97), g=st.floats(0.0, 0.95), mu_sun=st.floats(0.66, 1.0),
       depth=st.floats(1.0, 8.0), seed=st.integers(0, 2**32 - 1))
def test_radiance_seen_integrates_to_the_photons_irradiances(a, albedo, g, mu_sun, depth, seed):
    """With no seabed a camera looking down sees the upwelling radiance itself: the path radiance over the lower
    hemisphere, cosine-weighted, is E_u as the photons' directions at their collisions tally it; over the upper
    hemisphere, with the window's sky and the direct sun, E_d. (The grid, its phase function, the single scattering
    and the ray integral against the photons' own record.)"""
    b = a * albedo / (1.0 - albedo)
    c = a + b
    col = solve(a, b, g, mu_sun, 1.0, 0.4, depth + 10.0 / a, np.random.default_rng(seed), photons=8000)
    i = int(np.clip(np.abs(col.z - depth).argmin(), 2, len(col.z) - 3))
    layers = np.arange(i - 2, i + 3)  # five layers' centres (the tallies are layer means): less of their noise
    x, wx = np.polynomial.legendre.leggauss(8)
    mu, phi = (x + 1.0) / 2.0, (np.arange(12) + 0.5) * (2.0 * math.pi / 12)
    cos_c = math.cos(math.radians(SNELL_CONE_DEG))
    m = cos_c + (1.0 - cos_c) * (x + 1.0) / 2.0
    seen = np.zeros(2)
    for z in col.z[layers]:
        for k, sign in enumerate((1.0, -1.0)):
            v = directions(np.arccos(sign * mu)[:, None], phi[None, :]).reshape(-1, 3)
            seen[k] += (path_radiance(col, v, z).reshape(8, 12) * (mu * wx / 2.0)[:, None]).sum() * (
                2.0 * math.pi / 12)
        # The window's unscattered sky (its edge is a step: quadrature over the window only) and the sun's layer mean.
        seen[0] += 2.0 * math.pi * 0.4 * (np.exp(-c * z / m) * m * wx).sum() * (1.0 - cos_c) / 2.0
        top, bottom = (math.exp(-c * (z + h * col.dz / 2.0) / mu_sun) for h in (-1.0, 1.0))
        seen[0] += mu_sun * mu_sun / (c * col.dz) * (top - bottom)
    # Bounds: the photons' noise in five layers' tallies (8000 photons), E_u's the larger (fewer photons go up).
    assert abs(seen[1] / col.e_u[layers].sum() - 1.0) < 0.12
    assert abs(seen[0] / col.e_d[layers].sum() - 1.0) < 0.06
