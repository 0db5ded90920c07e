"""The seabed's light in the water above it, for the solved water (`solved`): what the seabed reflects is scattered
into view rays once or more, and what the deep water below would have sent up is not.

The open column (`unit_columns.unit_column`) is infinitely deep: its upwelling light comes from water below the
seabed. Over a seabed of mean albedo A at depth D, the light leaving the seabed's plane upwards is A E_d(D) instead
of the open column's E_u(D): the seabed scatters into the water above as a Lambertian plane of exitance A E_d(D)
(`unit_columns.seabed_column`, unit exitance, scaled), and what deep water would have sent up is taken off as a
plane of exitance E_u(D) with the angular shape of deep water's upwelling light (`unit_columns.upwelling_shape`).
A surface seen by the camera is then attenuated by the beam's c alone, its forward-scattered light being in J_ms
through the seabed's mean exitance (counted once; the per-pixel detail is not blurred).

Not modelled: the seabed's relief and shadows in its mean exitance, light reflected by the seabed more than once,
and the water surface over the seabed column (its upward light leaves through the surface unreflected anyway).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from seasynth.worker.light.column import Column
from seasynth.worker.light.unit_columns import NODES_THETA, reliable_depth, seabed_column, seabed_profile

MIN_RISE = 1.0  # optical depths: looking up, the seabed's J is followed at least this far (more: the camera's height)
# Looking down, J grows towards the seabed; the view ray's rate c - K_J w_z is kept at least (1 - MAX_GROWTH) c at
# every direction the node's rate is interpolated to (so a ray's integral stays finite and nothing overflows).
MAX_GROWTH = 0.95
RAY_NODES = 129  # nodes of the quadrature along a ray down to the seabed that a node's rate is matched to
HEIGHT_NODES = 48  # heights of the seabed's table, 0 to its column's reliable height evenly in the square root


def growth_floor() -> np.ndarray:
    """(NODES_THETA,) the least K_J / c a view-table node may take: -MAX_GROWTH / |w_z| of the steepest direction
    interpolated from the node (the next node towards the vertical) looking down, -1 looking up (such a ray ends at
    the surface)."""
    polar = np.radians(np.linspace(0.0, 180.0, NODES_THETA))
    steepest = np.abs(np.cos(np.minimum(polar + np.radians(180.0 / (NODES_THETA - 1)), math.pi)))
    return np.where(polar > math.pi / 2 + 1e-9, -MAX_GROWTH / np.maximum(steepest, 1e-9), -1.0)


def _log_at(col: Column, values: np.ndarray, tau, kappa: float) -> np.ndarray:
    """log of `values` (nz, ...) (positive) at optical depths tau (scalar or (n,)): linear in log between layer
    centres, the first layer's value above it, past the column's reliable depth continued at the diffuse rate
    kappa. Returns (...) or (n, ...)."""
    reliable = reliable_depth(col, kappa)
    tau = np.asarray(tau, np.float64)
    t = np.clip(tau, float(col.z[0]), reliable)
    logs = np.log(np.maximum(values, 1e-300))
    i = np.clip(np.searchsorted(col.z, t) - 1, 0, len(col.z) - 2)
    f = ((t - col.z[i]) / (col.z[i + 1] - col.z[i])).reshape(t.shape + (1,) * (logs.ndim - 1))
    past = (kappa * np.maximum(tau - reliable, 0.0)).reshape(f.shape)
    return logs[i] * (1.0 - f) + logs[i + 1] * f - past


def exitances(sun: float, sky: float, tau: float, kappa: float, sun_col: Column | None,
              sky_col: Column | None) -> tuple[float, float]:
    """pi (E_d, E_u) at the seabed's optical depth tau in the open column, in the renderer's units. sun, sky: the
    unit columns' scales (SolvedWater.sun, .sky), a column None where its light is off."""
    e_d = e_u = 0.0
    for scale, col in ((sun, sun_col), (sky, sky_col)):
        if col is None or scale <= 0.0:
            continue
        e_d += scale * math.exp(float(_log_at(col, col.e_d, tau, kappa)))
        e_u += scale * math.exp(float(_log_at(col, col.e_u, tau, kappa)))
    return e_d, e_u


def seabed_j(omega: float, g: float, tau_h: float, kappa: float,
             upwelling: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(J (NODES_THETA,), its rate of decrease with depth K_J (NODES_THETA,)) per unit exitance of the seabed, at the
    camera's optical height tau_h over it, on the view table's polar nodes (from the zenith; the seabed's light is
    the same at every azimuth), in optical units (per unit c): `_at_height` on HEIGHT_NODES heights, kept per
    process, interpolated (log J and K_J linearly in the height's square root, which is dense near the seabed)."""
    heights, log_j, k = _height_table(omega, g, kappa, upwelling)
    x = math.sqrt(max(tau_h, 0.0))
    xs = np.sqrt(heights)
    i = int(np.clip(np.searchsorted(xs, x) - 1, 0, len(xs) - 2))
    f = min(max((x - xs[i]) / (xs[i + 1] - xs[i]), 0.0), 1.0)
    past = kappa * max(tau_h - heights[-1], 0.0)  # above the table: on at the diffuse rate
    return np.exp(log_j[i] * (1.0 - f) + log_j[i + 1] * f - past), k[i] * (1.0 - f) + k[i + 1] * f


@functools.lru_cache(maxsize=64)
def _height_table(omega: float, g: float, kappa: float, upwelling: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    col = seabed_column(omega, g, upwelling)
    heights = np.linspace(0.0, math.sqrt(reliable_depth(col, kappa)), HEIGHT_NODES) ** 2
    rows = [_at_height(col, seabed_profile(omega, g, upwelling), float(h), kappa) for h in heights]
    log_j = np.log(np.maximum(np.array([r[0] for r in rows]), 1e-300))
    return heights, log_j, np.array([r[1] for r in rows])


def _at_height(col: Column, prof: np.ndarray, h: float, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """seabed_j at one height: J from the column's layers; looking down, K_J is the one whose exponential gives the
    node's ray its integral of J exp(-t) down to the seabed (quadrature over the column's layers), within
    `growth_floor`; looking up, the secant of log J from the camera's height to MIN_RISE or the camera's height above
    it, whichever is more."""
    j = np.exp(_log_at(col, prof, h, kappa))
    hi = min(h + max(h, MIN_RISE), reliable_depth(col, kappa))
    up = (_log_at(col, prof, hi, kappa) - np.log(np.maximum(j, 1e-300))) / (hi - h) if hi > h + 1e-9 \
        else np.zeros_like(j)
    polar = np.radians(np.linspace(0.0, 180.0, NODES_THETA))
    looking_up = polar < math.pi / 2 - 1e-9
    down = _matched_rates(col, prof, h, -np.cos(polar), kappa, j) if h > 0.0 else np.zeros_like(j)
    return j, np.clip(np.where(looking_up, up, down), growth_floor(), 1.0)


def _matched_rates(col: Column, prof: np.ndarray, h: float, mu: np.ndarray, kappa: float,
                   j_h: np.ndarray) -> np.ndarray:
    """(NODES_THETA,) per node looking down (mu = -w_z > 0) the K_J such that j_h integral_0^D exp(-(1 + K_J mu) s) ds
    is the integral of J(h - s mu) exp(-s) ds along its ray from height h to the seabed, D = h / mu (optical units,
    trapezoids on RAY_NODES nodes); 0 for the other nodes and where J is 0."""
    out = np.zeros(len(mu))
    nodes = np.flatnonzero((mu > 1e-9) & (j_h > 0.0))
    if nodes.size == 0:
        return out
    d = h / mu[nodes]  # (n,)
    s = np.linspace(0.0, 1.0, RAY_NODES)[None, :] * d[:, None]  # (n, RAY_NODES)
    logs = _log_at(col, prof[:, nodes], (h - s * mu[nodes, None]).ravel(), kappa)  # (n * RAY_NODES, n)
    own = logs.reshape(len(nodes), RAY_NODES, len(nodes))[np.arange(len(nodes)), :, np.arange(len(nodes))]
    f = np.exp(own - s)
    target = np.sum(0.5 * (f[:, 1:] + f[:, :-1]) * np.diff(s, axis=1), axis=1) / j_h[nodes]
    # (1 - exp(-alpha d)) / alpha falls with alpha from d: bisect alpha on a log scale
    lo, hi = np.full(len(nodes), 1e-6), np.full(len(nodes), 1e3)
    for _ in range(60):
        mid = np.sqrt(lo * hi)
        above = -np.expm1(-mid * d) / mid > target
        lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    out[nodes] = (np.sqrt(lo * hi) - 1.0) / mu[nodes]
    return out
