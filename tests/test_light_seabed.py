"""Tests of the seabed's light in the solved water (`seasynth.worker.light.seabed`): the seabed column against the
single scattering of a Lambertian plane and against the diffuse attenuation K, the view table's seabed part (its
rates give each node's ray its integral, it is affine in the albedo and vanishes far above the seabed), the lamps'
light on surfaces through K, and a material's mean albedo factor."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_render import draw
from test_render_light import CLEAR, SCATTERING, camera, lamp, light, quad

from seasynth.worker.light import Medium, hg
from seasynth.worker.light.seabed import _log_at, growth_floor, seabed_j
from seasynth.worker.light.solved import LAMP_SEEN_CAP, NODES_THETA, SolvedWater
from seasynth.worker.light.unit_columns import diffuse_rate, seabed_column, seabed_profile
from seasynth.worker.render import Image, Material, Sampling
from seasynth.worker.scene.materials import albedo_factor

POLAR = np.radians(np.linspace(0.0, 180.0, NODES_THETA))


def single_scattering(omega: float, g: float, h: float, polar: float) -> float:
    """J per unit exitance at optical height h over a Lambertian plane (radiance 1/pi), scattered once, for a view
    looking at `polar` from the zenith: omega integral over the lower hemisphere of HG(w . s) exp(-h / |s_z|) / pi."""
    x, wx = np.polynomial.legendre.leggauss(400)
    mu = 0.5 * (x + 1.0)  # |s_z| of light arriving from below
    phi = (np.arange(256) + 0.5) * (2 * math.pi / 256)
    s = np.stack([np.sqrt(1 - mu**2)[:, None] * np.cos(phi), np.sqrt(1 - mu**2)[:, None] * np.sin(phi),
                  -np.broadcast_to(mu[:, None], (len(mu), len(phi)))], axis=-1)
    w = np.array([math.sin(polar), 0.0, math.cos(polar)])
    f = hg(s @ w, g) * np.exp(-h / mu)[:, None] / math.pi
    return omega * float((f.sum(axis=1) * (2 * math.pi / 256) * 0.5 * wx).sum())


@pytest.mark.parametrize("g", [0.0, 0.7])
@pytest.mark.parametrize("h", [0.5, 2.0])
def test_the_seabed_column_is_a_lambertian_planes_single_scattering_where_little_scatters_twice(g, h):
    """At omega 0.02 light scattered twice is ~2% of the once: the column's J on the view nodes, the right way up
    (looking down sees the plane's light scattered forwards), is the plane's single scattering, within the photon
    noise and the nodes' box means (10%; looking down at g 0.7 J is ~30x looking up)."""
    omega = 0.02
    kappa = diffuse_rate(omega, g)
    col = seabed_column(omega, g)
    got = np.exp(_log_at(col, seabed_profile(omega, g, False), h, kappa))
    want = np.array([single_scattering(omega, g, h, p) for p in POLAR])
    np.testing.assert_allclose(got, want, rtol=0.1)
    if g > 0:
        assert got[-1] > 10 * got[0]


@pytest.mark.parametrize("omega", [0.5, 0.87, 0.955])
def test_a_uniform_seabed_seen_straight_down_keeps_its_forward_scattered_light_as_the_diffuse_k_says(omega):
    """A Lambertian seabed of radiance L seen straight down from h: L exp(-c h) unscattered plus the seabed
    column's path integral. Gordon's diffuse attenuation (Medium.k, an independent model of the same light) has
    the whole as L exp(-K h): the two agree within 8% of L at g 0.92 from 0.25 to 2 optical depths (measured:
    0.2-5%)."""
    g = 0.92
    kappa = diffuse_rate(omega, g)
    k = float(Medium(a=np.array([1 - omega]), b=np.array([omega]), g=g, surface_z=0.0).k[0])
    col, prof = seabed_column(omega, g), seabed_profile(omega, g, False)
    for h in (0.25, 0.5, 1.0, 2.0):
        t = np.linspace(0.0, h, 4001)
        f = np.exp(_log_at(col, prof[:, -1], h - t, kappa)) * np.exp(-t)
        scattered = math.pi * float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(t)))
        assert abs(math.exp(-h) + scattered - math.exp(-k * h)) < 0.08


@settings(max_examples=40, deadline=None)
@given(h=st.floats(0.0, 6.0), node=st.integers(10, 18), omega=st.sampled_from([0.5, 0.87, 0.955]),
       upwelling=st.booleans())
def test_a_nodes_rate_gives_its_ray_down_to_the_seabed_the_columns_integral(h, node, omega, upwelling):
    """Looking down, the table's J and K_J at the camera's height make J exp(-(1 + K_J mu) s) on the node's ray,
    whose integral to the seabed is the column's own (quadrature along the ray) within 4% (the height table's
    interpolation; exact at its nodes), and never below growth_floor. Measured over h from 0.05 to 6 by 0.025, every
    node and these waters: at most 3.75% (omega 0.955, h 3.2, node 10, the most grazing ray down); 3% failed there."""
    g = 0.92
    kappa = diffuse_rate(omega, g)
    col, prof = seabed_column(omega, g, upwelling), seabed_profile(omega, g, upwelling)
    j, k = seabed_j(omega, g, h, kappa, upwelling)
    assert (k >= growth_floor() - 1e-12).all() and (k <= 1.0).all() and (j > 0).all()
    mu = -math.cos(POLAR[node])
    if h < 0.05 or k[node] <= growth_floor()[node] + 1e-9:
        return  # nothing to integrate, or the rate is held at its floor (then the model's integral is below)
    s = np.linspace(0.0, h / mu, 4001)
    f = np.exp(_log_at(col, prof[:, node], h - s * mu, kappa)) * np.exp(-s)
    want = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(s)))
    alpha = 1.0 + k[node] * mu
    got = j[node] * -math.expm1(-alpha * h / mu) / alpha
    assert got == pytest.approx(want, rel=0.04)


def _table(albedo: float, seabed_depth: float, cam_depth: float):
    lt = light(CLEAR, SCATTERING, surface_z=seabed_depth)
    w = SolvedWater(medium=lt.medium, sun_dir_world=lt.sun_dir_world, sun=np.full(3, math.pi), sky=np.full(3, 0.4),
                    seabed_albedo=np.full(3, albedo), seabed_depth_m=seabed_depth)
    return w.view_table(cam_depth)


@settings(max_examples=25, deadline=None)
@given(a1=st.floats(0.0, 1.0), a2=st.floats(0.0, 1.0), height=st.floats(0.0, 5.0))
def test_the_seabed_part_is_affine_in_the_albedo_and_brighter_seabeds_light_the_water_more(a1, a2, height):
    """J_ms over a seabed is the open column's less deep water's upwelling plus albedo x E_d x the Lambertian
    column's: affine in the albedo, so a brighter seabed never darkens a node looking down (where J_ms stays
    positive) and J_ms at albedo (a1 + a2) / 2 is the mean of the two."""
    lo, hi = sorted((a1, a2))
    t_lo, t_hi, t_mid = (_table(a, 12.0, 12.0 - height) for a in (lo, hi, 0.5 * (lo + hi)))
    down = POLAR > math.pi / 2
    assert (t_hi.j[down] >= t_lo.j[down] - 1e-12).all()
    positive = (t_lo.j > 0) & (t_hi.j > 0)
    np.testing.assert_allclose(t_mid.j[positive], 0.5 * (t_lo.j + t_hi.j)[positive], rtol=1e-9)


def test_far_above_the_seabed_the_water_is_the_open_columns():
    """A camera 10 m down over a seabed twenty diffuse lengths (the channel with the longest) further down: its light
    has gone, the table is the open column's to 1%, whatever the albedo; a metre over it the seabed changes it."""
    lt = light(CLEAR, SCATTERING, surface_z=10.0)
    reach = 20.0 / float(lt.medium.k.min())
    open_w = SolvedWater(medium=lt.medium, sun_dir_world=lt.sun_dir_world, sun=np.full(3, math.pi),
                         sky=np.full(3, 0.4))
    bare = open_w.view_table(10.0)
    assert (bare.j > 0).all()
    for albedo in (0.0, 0.3, 1.0):
        np.testing.assert_allclose(_table(albedo, 10.0 + reach, 10.0).j, bare.j, rtol=0.01)
    assert (_table(1.0, 11.0, 10.0).j[-1] > 1.5 * bare.j[-1]).all()


def test_a_lamp_lit_surface_is_seen_through_k_with_the_solved_column(renderer):
    """The surface pass weights the lamps' light on a surface by exp((c - K) r) (capped at LAMP_SEEN_CAP) where the
    solved column is on, so the resolve's exp(-c r) leaves exp(-K r): with the sun and sky all but off, the
    surface's J with the column over its J without is that factor, sample by sample (to half-float rounding)."""
    view, _ = camera([0.0, -1.0, 1.2], [0.0, 3.0, 0.0], 60.0)
    floor = [draw("test/seabed/floor", quad([[-9, -2, 0], [9, -2, 0], [9, 12, 0], [-9, 12, 0]]), 0)]
    lt = light([0.2, 0.1, 0.05], [0.3, 0.4, 0.5], surface_z=10.0, e0=np.full(3, 1e-12), esky=1e-12,
               lamps=(lamp((0.0, 0.0, 0.0), (0.0, 0.3, 1.0), cutoff_deg=60.0),))
    from seasynth.worker.light.solved import with_column

    on, off = with_column(lt), with_column(lt, False)
    assert on.terms.solved and not off.terms.solved
    one = Sampling(msaa=1, supersample=1)
    j_on, r_on = renderer.samples(view, floor, on, one)
    j_off, r_off = renderer.samples(view, floor, off, one)
    np.testing.assert_array_equal(r_on, r_off)
    lit = np.isfinite(r_on[0]) & (j_off[0].astype(np.float64).min(axis=-1) > 1e-3)
    assert lit.sum() > 200
    r = r_on[0][lit][:, None]
    factor = np.exp(np.minimum((lt.medium.c - lt.medium.k) * r, LAMP_SEEN_CAP))
    np.testing.assert_allclose(j_on[0][lit].astype(np.float64), j_off[0][lit].astype(np.float64) * factor,
                               rtol=4e-3)


def _image(key: str, pixels: np.ndarray, srgb: bool) -> Image:
    return Image(key=key, pixels=pixels.astype(np.uint8), srgb=srgb, source=key)


def test_a_materials_albedo_factor_is_its_maps_means_and_its_normals_mean_tilt():
    """Base map of one colour, occlusion, metallic and a normal map tilted by a known angle: the factor is the
    decoded colour x gain x (1 - metallic blue) x occlusion x cos of the tilt, exactly (to 8-bit texels)."""
    n = 16
    base = _image("b", np.full((n, n, 3), [200, 100, 50]), True)
    orm = _image("o", np.full((n, n, 3), [204, 255, 51]), False)
    tilt = math.radians(30.0)
    texel = np.round((np.array([math.sin(tilt), 0.0, math.cos(tilt)]) + 1.0) / 2.0 * 255.0)
    normal = _image("n", np.broadcast_to(texel, (n, n, 3)), False)
    m = Material(base=base, base_gain=1.5, normal=normal, orm=orm, occlusion_strength=0.5, metallic_factor=0.5)
    decoded = ((np.array([200, 100, 50]) / 255.0 + 0.055) / 1.055) ** 2.4
    t = texel / 255.0 * 2.0 - 1.0
    want = decoded * 1.5 * (1.0 - 0.5 * 51 / 255) * (1.0 + 0.5 * (204 / 255 - 1.0)) * t[2] / np.linalg.norm(t)
    np.testing.assert_allclose(albedo_factor(m), want, rtol=1e-6)
    np.testing.assert_array_equal(albedo_factor(None), np.ones(3))
    flat = dataclasses.replace(m, normal=_image("f", np.full((n, n, 3), [128, 128, 255]), False), orm=None)
    np.testing.assert_allclose(albedo_factor(flat), decoded * 1.5, rtol=1e-4)
