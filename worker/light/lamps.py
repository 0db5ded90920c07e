"""Lamps on the vehicle: spot lights fixed to the camera. Their profile is the path tracer's (Mitsuba's `spot`):
full intensity within the beam width, falling linearly in angle to 0 at the cutoff.

Light from a lamp reaching a point d metres away at angle theta off its axis (`light_factor`, times I / d^2):

    exp(-c d) P(theta; beam, cutoff)  +  (exp(-K d) - exp(-c d)) N P(theta; lo', hi')

The first part is the unscattered beam, with the lamp's sharp profile P. The second is the light scattered forwards
on the way, still travelling outwards (K, `Medium.k`, is what a broad forward light field loses per metre), but
spread in angle: scattered at least once, it was scattered n = b d / (1 - exp(-b d)) times on average, each time
turned by the phase function's mean square angle 2 (1 - g) (small angles: <cos> = g), and a turn at a point spread
uniformly along the path moves the light's apparent direction, seen from the lamp, by a third of that in variance
(Fermi's relation for lateral spread), so by s^2 = (1 - g) n / 3 per axis. The profile's linear edge of width
w = cutoff - beam, whose variance is w^2 / 12, widens to w' = sqrt(w^2 + 12 s^2) about its middle m (lo' and hi'
clamped to [0, pi]), and N keeps the scattered light's power: N = E(beam, cutoff) / E(lo', hi') with E the
profile's solid angle over 2 pi, 1 - cos(m) sinc(w / 2) (the mean of 1 - cos over the edge). In clear water
K = c and the second part vanishes; in turbid water it is the glow round the beam and most of the light inside it
(against a path tracer, `seasynth bench fidelity`).
"""

from __future__ import annotations

import math

import numpy as np

from seasynth.service.spec.light import Lamp as LampSpec
from seasynth.worker.light import Lamp

# Quadrature nodes of the lamp's single-scattering integral along each view ray, in the equiangular variable
# (Kulla & Fajardo 2012), which turns the inverse-square peak near the lamp into a smooth integrand.
BACKSCATTER_NODES = 24
# The integral stops where light has crossed this many diffuse attenuation lengths (exp(-16) = 1e-7): open water.
CUTOFF_OPTICAL_DEPTH = 16.0
# A pixel's lamp scattering is integrated once, to the mean of its samples' ray ends, where those differ by at most
# this fraction of the nearest (volume.volume_pixels, and the resolve shader): the integral is smooth in its end, and
# its error there is second order in the spread (under 3e-6 linear against per-sample integration at 5%, in the
# tests' lamp scenes: a receding seabed's samples span 3-4% of their range); elsewhere (silhouettes) once a sample.
LAMP_Z_SPREAD = 0.05
# The backscatter integral runs over the part of each ray inside the cone that the lamp's light reaches
# (`reach`, `cone_interval`), widened by this margin against rounding: its nodes fall where the light is.
REACH_MARGIN_RAD = 0.01
# Lamp light is spread (Terms.lamp_spread) when the forward-scattered share it redistributes reaches this much of a
# lamp's light at this distance in some channel, 1 - exp(-(c - K) d): in clear ocean water (Jerlov I: 2% of the blue
# at 10 m) spreading changed the fidelity bench's clear-lamps frame by 0.01 dB and cost half its time.
SPREAD_MIN_SHARE = 0.05
SPREAD_DISTANCE_M = 10.0
# Rays closer than this to the lamp (metres) use it: the lamp is a point, its glow finite in any real image.
MIN_LAMP_DISTANCE_M = 1e-3


def lamp_from_spec(spec: LampSpec, intensity: float) -> Lamp:
    d = np.asarray(spec.direction, dtype=np.float64)
    return Lamp(
        position_cam=np.asarray(spec.offset_m, dtype=np.float64),
        direction_cam=d / np.linalg.norm(d),
        cutoff_rad=math.radians(spec.cutoff_deg),
        beam_rad=math.radians(spec.beam_width_deg),
        intensity=np.asarray(spec.colour, dtype=np.float64) * intensity,
    )


def _ramp(ang: np.ndarray, lo, hi) -> np.ndarray:
    return np.clip((hi - ang) / np.maximum(hi - lo, 1e-9), 0.0, 1.0)


def _edge_energy(lo, hi):
    """E(lo, hi): the solid angle of a profile that is 1 to lo and falls linearly to 0 at hi, over 2 pi. Written
    as 2 sin^2(m / 2) + cos(m) (1 - sinc(x)), x the half width, to keep narrow cones exact in float32 (the shader's
    twin)."""
    m, x = 0.5 * (lo + hi), 0.5 * (hi - lo)
    x2 = x * x
    with np.errstate(divide="ignore", invalid="ignore"):
        one_minus_sinc = np.where(x < 0.1, x2 / 6.0 * (1.0 - x2 / 20.0), 1.0 - np.sin(x) / np.maximum(x, 0.1))
    return 2.0 * np.sin(0.5 * m) ** 2 + np.cos(m) * one_minus_sinc


def _widened_edges(lamp: Lamp, g: float, bd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo', hi'): the profile's edge widened for light that crossed b d scattering lengths (module docstring)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.where(bd < 1e-4, 1.0, bd / -np.expm1(-np.maximum(bd, 1e-4)))
    w = lamp.cutoff_rad - lamp.beam_rad
    m = 0.5 * (lamp.cutoff_rad + lamp.beam_rad)
    w2 = np.sqrt(w * w + 4.0 * (1.0 - g) * n)  # 12 s^2 = 4 (1 - g) n
    return np.maximum(m - 0.5 * w2, 0.0), np.minimum(m + 0.5 * w2, math.pi)


def light_factor(lamp: Lamp, cos_axis: np.ndarray, d: np.ndarray, c: np.ndarray, K: np.ndarray, b: np.ndarray,
                 g: float, spread: bool = True) -> np.ndarray:
    """The module docstring's factor per channel, (..., 3) float64, for cos_axis and d (...) (d > 0 metres).
    spread=False (Terms.lamp_spread off): the forward-scattered light stays in the sharp profile, exp(-K d) P."""
    ang = np.arccos(np.clip(cos_axis, -1.0, 1.0))[..., None]
    d = np.asarray(d, dtype=np.float64)[..., None]
    if not spread:
        return np.exp(-K * d) * _ramp(ang, lamp.beam_rad, lamp.cutoff_rad)
    direct = np.exp(-c * d)
    out = direct * _ramp(ang, lamp.beam_rad, lamp.cutoff_rad)  # profile()
    lo, hi = _widened_edges(lamp, g, b * d)
    widened = cone_energy(lamp) / _edge_energy(lo, hi) * _ramp(ang, lo, hi)  # N P(theta; lo', hi')
    return out + (np.exp(-K * d) - direct) * widened


def reach(lamp: Lamp, c: np.ndarray, K: np.ndarray, b: np.ndarray, g: float, d_max, spread: bool = True
          ) -> np.ndarray:
    """The half angle (rad) beyond which `light_factor` is exactly 0 at every distance up to d_max: the cutoff, or
    the widest channel's spread edge hi' when scattered light is kept (K < c) and spread. Plus REACH_MARGIN_RAD."""
    d_max = np.asarray(d_max, dtype=np.float64)
    if not spread or not np.any(K < c):
        return np.full(d_max.shape, lamp.cutoff_rad + REACH_MARGIN_RAD)
    _, hi = _widened_edges(lamp, g, float(np.max(b)) * d_max)
    return np.maximum(hi, lamp.cutoff_rad) + REACH_MARGIN_RAD


def dot3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x . y over the last axis (3), written out: each element rounds alike whatever the array's shape and the CPU
    (matmul, einsum and norm pick their kernels by both, so a ray's value moved with the rays beside it)."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


def norm3(x: np.ndarray) -> np.ndarray:
    """|x| over the last axis (3), as dot3 rounds."""
    return np.sqrt(dot3(x, x))


def cone_interval(dirs: np.ndarray, apex: np.ndarray, axis: np.ndarray, half_angle: np.ndarray,
                  t_end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t0, t1): the part of each ray t * dirs, 0 <= t <= t_end, inside the cone (apex, unit axis, half_angle); t0 = t1
    when none. A cone of half angle >= 90 degrees is not convex: the whole ray is returned.

    The line meets the cone's surface where (t A + B)^2 = cos^2 (t^2 + 2 t C + D) (q = -apex, A = dirs.axis,
    B = q.axis, C = dirs.q, D = q.q). Those roots (stable form) and the ends split [0, t_end] into pieces; the cone
    being convex, the pieces whose middles lie inside are one interval. A root off by rounding moves a bound by as
    much, where `reach`'s margin keeps the light at 0."""
    q = -np.asarray(apex, dtype=np.float64)
    k = np.cos(np.minimum(half_angle, math.pi / 2))
    A, B, C, D = dot3(dirs, axis), float(dot3(q, axis)), dot3(dirs, q), float(dot3(q, q))
    a2, b2, c2 = A * A - k * k, A * B - k * k * C, B * B - k * k * D
    sq = np.sqrt(np.maximum(b2 * b2 - a2 * c2, 0.0))
    qq = -(b2 + np.where(b2 < 0, -sq, sq))
    tiny = 1e-30
    r1 = qq / np.where(np.abs(a2) < tiny, tiny, a2)
    r2 = c2 / np.where(np.abs(qq) < tiny, tiny, qq)
    cuts = np.sort(np.stack([np.zeros_like(t_end), np.clip(r1, 0, t_end), np.clip(r2, 0, t_end), t_end]), axis=0)
    t0, t1 = np.full(t_end.shape, np.inf), np.full(t_end.shape, -np.inf)
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        mid = 0.5 * (lo + hi)
        v = dirs * mid[..., None] + q
        inside = (mid * A + B) >= k * norm3(v)
        t0, t1 = np.where(inside, np.minimum(t0, lo), t0), np.where(inside, np.maximum(t1, hi), t1)
    whole = half_angle >= math.pi / 2
    empty = t0 > t1
    return (np.where(whole, 0.0, np.where(empty, 0.0, t0)), np.where(whole, t_end, np.where(empty, 0.0, t1)))


def spread_worthwhile(c: np.ndarray, K: np.ndarray) -> bool:
    """Whether spreading lamp light changes a frame: see SPREAD_MIN_SHARE."""
    return bool(-math.expm1(-float(np.max(c - K)) * SPREAD_DISTANCE_M) >= SPREAD_MIN_SHARE)


def profile(lamp: Lamp, cos_angle: np.ndarray) -> np.ndarray:
    """Spot falloff in [0, 1] for the cosine of the angle off the lamp's axis; any shape, float64."""
    return _ramp(np.arccos(np.clip(cos_angle, -1.0, 1.0)), lamp.beam_rad, lamp.cutoff_rad)


def cone_energy(lamp: Lamp) -> float:
    """The lamp's profile's solid angle over 2 pi (N's numerator in the module docstring)."""
    return float(_edge_energy(lamp.beam_rad, lamp.cutoff_rad))
