"""The physical model's water along view rays, in float64: the numpy twin of the resolve shader (`glsl.VOLUME`).

Per sample and channel, with K the diffuse attenuation (see `Medium.k`):

    I = J exp(-K z) + b * sum_terms P_term E_term integral_0^z' exp(-K t) exp(-k_term depth(t)) dt  + lamps + window

(the sky's P_term is its phase function integrated over Snell's window, `sky.sky_phase`)

depth(t) = D_c - t w_z (camera depth D_c, ray direction w, z up), z' = z cut at the water surface. Each term's
integral is closed-form (`segment`); a lamp's single scattering is integrated numerically (`lamps.BACKSCATTER_NODES`
nodes in the equiangular variable).

With the solved column (`Terms.solved`, `solved`), the sun's and the sky's terms are their single scattering (c in
place of K on both legs: the unscattered beam, the unscattered view ray) and the multiply scattered rest is
J_ms(w) integral_0^z' exp(-(c - K_J w_z) t) dt from the column's table at the camera's depth; the window's sky is
seen through c too, and so is a surface: the sun's and sky's light a seabed reflects is scattered towards the camera
through J_ms (`seabed`), and the lamps' light on a surface comes weighted by exp((c - K) r) from the surface pass
(`solved.LAMP_SEEN_CAP`), so it reaches the camera through K as the lamps' own model has it.
"""

from __future__ import annotations

import math

import numpy as np

from seasynth.worker.light import SNELL_CONE_DEG, PhysicalLight, hg
from seasynth.worker.light.lamps import (
    BACKSCATTER_NODES,
    CUTOFF_OPTICAL_DEPTH,
    LAMP_Z_SPREAD,
    MIN_LAMP_DISTANCE_M,
    cone_interval,
    dot3,
    light_factor,
    norm3,
    reach,
)
from seasynth.worker.light.sky import MU_SKY, sky_phase, sky_phase_table, window_radiance
from seasynth.worker.light.solved import lookup

_SMALL = 1e-2  # |alpha z| below this: the series of (1 - exp(-x)) / x to x^3 (truncation < 1e-10)


def segment(x1: np.ndarray, alpha: np.ndarray, z: np.ndarray) -> np.ndarray:
    """integral_0^z exp(-x1 - alpha t) dt for x1 >= 0, x1 + alpha z >= 0 (so nothing overflows), z >= 0 or +inf
    (then alpha > 0). Stable at alpha -> 0 and for huge optical depths; arrays broadcast."""
    x1, alpha, z = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x1, alpha, z)))
    zf = np.where(np.isfinite(z), z, 0.0)
    y = alpha * zf
    small = np.abs(y) < _SMALL
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        big = np.where(small, 0.0, (np.exp(-x1) - np.exp(-(x1 + y))) / np.where(small, 1.0, alpha))
        series = zf * np.exp(-x1) * (1.0 - y * (0.5 - y * (1.0 / 6.0 - y / 24.0)))
        inf = np.exp(-x1) / np.where(alpha > 0, alpha, 1.0)
    return np.where(np.isfinite(z), np.where(small, series, big), np.where(alpha > 0, inf, 0.0))


def distance_to_surface(dirs_world: np.ndarray, cam_depth: float) -> np.ndarray:
    """(...) metres along each unit view direction (..., 3) (world, z up) to the water surface; +inf looking level or
    down."""
    wz = dirs_world[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(wz > 0, cam_depth / np.where(wz > 0, wz, 1.0), np.inf)


def volume(J: np.ndarray, z: np.ndarray, dirs_world: np.ndarray, dirs_cam: np.ndarray, cam_depth: float,
           light: PhysicalLight, lamp_scattering: bool = True) -> np.ndarray:
    """I for samples: J (..., 3) linear, z (...) metres (+inf: no surface), dirs_world/dirs_cam (..., 3) unit view
    directions in the world (z up) and camera frames. Returns (..., 3) float64. lamp_scattering=False leaves the
    lamps' single scattering out (volume_pixels adds it a pixel at a time, as the resolve shader does)."""
    m = light.medium
    K, b = m.k, m.b
    t = light.terms
    V = m.c if t.solved else K  # the view leg's attenuation: the beam's c once J_ms carries the scattered rest
    z = np.asarray(z, dtype=np.float64)
    wz = dirs_world[..., 2]
    to_surface = distance_to_surface(dirs_world, cam_depth)
    zs = np.minimum(z, to_surface)[..., None]
    out = np.where(np.isfinite(z)[..., None], np.asarray(J, np.float64) * np.exp(-V * np.where(
        np.isfinite(z), z, 0.0)[..., None]), 0.0)
    w = wz[..., None]
    if t.scattering and t.solved and (t.sun or t.sky):
        j_ms, k_j = lookup(light.column.view_table(cam_depth, t.sun, t.sky), dirs_world, light.sun_dir_world)
        out = out + j_ms * segment(0.0, m.c - k_j * w, zs)
    if t.scattering and t.sun:
        s = light.sun_dir_world
        mu_s = dot3(dirs_world, s)[..., None]
        mu_w = s[2]
        e = math.pi * light.sun_irradiance
        # The beam and its forward-scattered light (small-angle: still along the sun's refracted direction) scatter
        # into the ray alike: the whole downwelling sun, attenuated by K, with the phase function's value.
        total = segment(V / mu_w * cam_depth, V - V / mu_w * w, zs)
        out = out + b * e * hg(mu_s, m.g) * total
    if t.scattering and t.sky:
        P = sky_phase(wz, sky_phase_table(m.g))[..., None]
        out = out + b * window_radiance(light.sky_irradiance) * P * segment(
            V / MU_SKY * cam_depth, V - V / MU_SKY * w, zs)
    if t.sky:
        # Open water looking up through Snell's window sees the sky itself.
        L = window_radiance(light.sky_irradiance)
        window = (~np.isfinite(z) & (wz > math.cos(math.radians(SNELL_CONE_DEG))))[..., None]
        with np.errstate(divide="ignore", over="ignore"):
            out = out + np.where(window, L * np.exp(-V * np.where(window, to_surface[..., None], 0.0)), 0.0)
    if t.scattering and lamp_scattering:
        for lamp in light.lamps[: t.lamps]:
            out = out + lamp_backscatter(lamp, dirs_cam, zs[..., 0], m, t.lamp_spread)
    return out


def volume_pixels(J: np.ndarray, z: np.ndarray, dirs_world: np.ndarray, dirs_cam: np.ndarray, cam_depth: float,
                  light: PhysicalLight) -> np.ndarray:
    """The mean of a pixel's samples as the resolve shader forms it: J (k, h, w, 3), z (k, h, w) for k samples
    looking along the pixel centre's ray (dirs (h, w, 3)). Every term per sample, except the lamps' scattering: once
    a pixel, to the mean of the samples' ray ends where those agree within LAMP_Z_SPREAD of the nearest (all equal
    included, open water too), else once a sample. Returns (h, w, 3) float64."""
    k = J.shape[0]
    acc = sum(volume(np.asarray(Jk, np.float64), zk, dirs_world, dirs_cam, cam_depth, light, lamp_scattering=False)
              for Jk, zk in zip(J, z))
    t, m = light.terms, light.medium
    if not (t.scattering and t.lamps):
        return acc / k
    ends = np.minimum(np.asarray(z, np.float64), distance_to_surface(dirs_world, cam_depth))  # (k, h, w)
    with np.errstate(invalid="ignore"):  # open water looking down: inf - inf
        lo, hi = ends.min(axis=0), ends.max(axis=0)
        once = (hi == lo) | (hi - lo <= LAMP_Z_SPREAD * lo)
        end = np.where(hi == lo, lo, ends.mean(axis=0))
    for lamp in light.lamps[: t.lamps]:
        per_pixel = k * lamp_backscatter(lamp, dirs_cam, end, m, t.lamp_spread)
        if once.all():
            acc = acc + per_pixel
            continue
        per_sample = sum(lamp_backscatter(lamp, dirs_cam, e, m, t.lamp_spread) for e in ends)
        acc = acc + np.where(once[..., None], per_pixel, per_sample)
    return acc / k


def lamp_backscatter(lamp, dirs_cam: np.ndarray, z: np.ndarray, m, spread: bool = True):
    """Single scattering of one lamp's light (`lamps.light_factor` on the lamp's leg, K on the camera's) towards
    the camera along rays (camera at the origin) up to z. dirs_cam (..., 3) unit, z (...) metres (finite or +inf),
    m the Medium. Returns (..., 3) float64."""
    K, b, g = m.k, m.b, m.g
    k_pos = K[b > 0]
    if k_pos.size == 0:
        return np.zeros((*z.shape, 3))
    t_end = np.minimum(z, CUTOFF_OPTICAL_DEPTH / max(float(k_pos.min()), 1e-30))
    p = lamp.position_cam
    d_max = np.maximum(norm3(p), norm3(dirs_cam * t_end[..., None] - p))
    t0, t1 = cone_interval(dirs_cam, p, lamp.direction_cam, reach(lamp, m.c, K, b, g, d_max, spread), t_end)
    tc = dot3(dirs_cam, p)  # along-ray position of the point nearest the lamp
    h = np.maximum(norm3(dirs_cam * tc[..., None] - p), MIN_LAMP_DISTANCE_M)
    u0 = np.arctan2(t0 - tc, h)
    u1 = np.arctan2(t1 - tc, h)
    du = (u1 - u0) / BACKSCATTER_NODES
    acc = np.zeros((*z.shape, 3))
    for i in range(BACKSCATTER_NODES):
        u = u0 + (i + 0.5) * du
        t = tc + h * np.tan(u)
        x = dirs_cam * t[..., None]
        to_x = x - p
        r = np.maximum(norm3(to_x), MIN_LAMP_DISTANCE_M)
        cos_axis = dot3(to_x, lamp.direction_cam) / r
        cos_scatter = -dot3(to_x, dirs_cam) / r
        f = hg(cos_scatter, g) / h  # inverse square * dt = du / h
        acc += f[..., None] * light_factor(lamp, cos_axis, r, m.c, K, b, g, spread) * np.exp(-K * t[..., None])
    return acc * (du[..., None] * b * math.pi * lamp.intensity)


def pixel_rays(K: np.ndarray, width: int, height: int, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit view directions through the pixel centres, as the resolve shader takes them: (dirs_world, dirs_cam),
    each (h, w, 3) float64 (camera frame KITTI: x right, y down, z forward; world z up)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    d = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d @ world_from_cam[:3, :3].T, d


def camera_depth(light: PhysicalLight, world_from_cam: np.ndarray) -> float:
    """The camera's depth below the water surface, metres (>= 0)."""
    return max(light.medium.surface_z - float(world_from_cam[2, 3]), 0.0)
