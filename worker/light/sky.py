"""Sky light under a flat surface: the sky's radiance fills Snell's window (a cone of half angle SNELL_CONE_DEG
about the zenith) and nothing else, and water scatters it into a view ray by the phase function.

Scattered into a ray looking along w, per metre and per unit b: L * P(w_z), with P(w_z) = integral over the window of
HG(s . w) ds (the scattering angle between light arriving from s and the ray's light going back to the camera).
Looking down, the window's light must scatter backwards, where HG with g ~ 0.9 is ~40x below isotropic; looking up
through the window, forwards. P depends on the ray only through w_z (the window is symmetric about the zenith): it
is tabulated once per g at SKY_PHASE_NODES values of w_z in [-1, 1] and read by linear interpolation, here and in
the resolve shader alike.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from seasynth.worker.light import SNELL_CONE_DEG, hg

MU_SKY = 0.84  # mean cosine of sky light under the surface: its paths are 1 / 0.84 longer than the depth
SKY_PHASE_NODES = 129  # w_z = -1, -1 + 2/128, ..., 1
_POLAR_NODES, _AZIMUTH_NODES = 48, 96  # quadrature over the window: < 1e-4 relative for g <= 0.95, ~20 ms
# Linear interpolation between the nodes misses P by < 0.7% at g = 0.92 (< 1.6% at 0.95), only where the window's edge
# sweeps through the phase function's peak (rays looking up at ~50 degrees off the zenith).


def window_radiance(sky_irradiance: np.ndarray) -> np.ndarray:
    """(3,) radiance inside Snell's window that gives `sky_irradiance` on a horizontal surface just below it."""
    return np.asarray(sky_irradiance, dtype=np.float64) / math.sin(math.radians(SNELL_CONE_DEG)) ** 2


@functools.lru_cache(maxsize=32)
def _table(g: float) -> np.ndarray:
    cos_c = math.cos(math.radians(SNELL_CONE_DEG))
    x, wx = np.polynomial.legendre.leggauss(_POLAR_NODES)
    mu = cos_c + (1.0 - cos_c) * (x + 1.0) / 2.0  # cos of the light's angle to the zenith
    w_mu = wx * (1.0 - cos_c) / 2.0
    phi = (np.arange(_AZIMUTH_NODES) + 0.5) * math.pi / _AZIMUTH_NODES  # half the circle: symmetric about w's plane
    wz = np.linspace(-1.0, 1.0, SKY_PHASE_NODES)
    cos_angle = (wz[:, None, None] * mu[None, :, None] + np.sqrt(1.0 - wz**2)[:, None, None]
                 * np.sqrt(1.0 - mu**2)[None, :, None] * np.cos(phi)[None, None, :])
    table = (hg(cos_angle, g) * w_mu[None, :, None]).sum(axis=(1, 2)) * (2.0 * math.pi / _AZIMUTH_NODES)
    table.flags.writeable = False
    return table


def sky_phase_table(g: float) -> np.ndarray:
    """(SKY_PHASE_NODES,) float64 P at w_z = linspace(-1, 1): the HG phase function (asymmetry g) integrated over
    Snell's window, in 1/sr * sr (dimensionless). Cached per g."""
    return _table(float(g))


def sky_phase(wz: np.ndarray, table: np.ndarray) -> np.ndarray:
    """P at view-direction z components `wz` (any shape) by linear interpolation in `table` (the shader's rule)."""
    x = (np.asarray(wz, dtype=np.float64) + 1.0) * ((SKY_PHASE_NODES - 1) / 2.0)
    i = np.clip(np.floor(x), 0, SKY_PHASE_NODES - 2).astype(np.int64)
    f = x - i
    return table[i] * (1.0 - f) + table[i + 1] * f
