"""The sun through the water column: refraction and Fresnel transmission at the flat surface, then attenuation with
depth; its unscattered part casts sharp shadows, the forward-scattered rest arrives from about the same direction."""

from __future__ import annotations

import math

import numpy as np

from seasynth.worker.light import WATER_INDEX

# Below this share of its surface irradiance the sun's unscattered beam is invisible in an 8-bit image (under
# half a code at full albedo), so no shadow map is drawn for it.
SHADOW_MIN_SHARE = 1.0 / 512


def fresnel_transmittance(cos_i: float, n: float = WATER_INDEX) -> float:
    """Unpolarised Fresnel transmittance from air into water at incidence cos_i (1 = normal), in [0, 1]."""
    cos_i = min(max(cos_i, 0.0), 1.0)
    sin_t = math.sqrt(max(1.0 - cos_i * cos_i, 0.0)) / n
    cos_t = math.sqrt(max(1.0 - sin_t * sin_t, 0.0))
    if cos_i <= 0.0:
        return 0.0
    rs = ((cos_i - n * cos_t) / (cos_i + n * cos_t)) ** 2
    rp = ((n * cos_i - cos_t) / (n * cos_i + cos_t)) ** 2
    return 1.0 - 0.5 * (rs + rp)


def refract_down(sun_dir_air: np.ndarray, n: float = WATER_INDEX) -> np.ndarray:
    """(3,) unit vector towards the sun as seen from under a flat surface (z up): Snell's law, azimuth kept."""
    s = np.asarray(sun_dir_air, dtype=np.float64)
    horizontal = math.hypot(s[0], s[1])
    sin_t = horizontal / n
    out = np.array([0.0, 0.0, 1.0]) if horizontal == 0 else np.array([s[0] / horizontal * sin_t,
                                                                     s[1] / horizontal * sin_t, 0.0])
    out[2] = math.sqrt(1.0 - sin_t * sin_t)
    return out


def sun_in_water(sun_dir_air: np.ndarray, intensity: float) -> tuple[np.ndarray, np.ndarray]:
    """(direction towards the sun under water (3,), irradiance just below the surface normal to the beam (3,)).
    A sun at or below the horizon gives zero irradiance."""
    s = np.asarray(sun_dir_air, dtype=np.float64)
    if s[2] <= 0.0 or intensity <= 0.0:
        return refract_down(np.array([0.0, 0.0, 1.0])), np.zeros(3)
    d = refract_down(s)
    # Horizontal irradiance I cos(i) crosses the surface as T I cos(i); normal to the refracted beam it is / cos(t).
    e = intensity * fresnel_transmittance(float(s[2])) * float(s[2]) / float(d[2])
    return d, np.full(3, e)


def shadow_worthwhile(c: np.ndarray, surface_depth_m: float, cos_w: float) -> bool:
    """Whether the sun's unscattered beam still matters at the shallowest point of the scene (depth in metres)."""
    return bool(np.exp(-np.min(c) * max(surface_depth_m, 0.0) / cos_w) >= SHADOW_MIN_SHARE)
