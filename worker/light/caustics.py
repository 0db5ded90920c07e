"""Caustics: the sun's unscattered beam focused by surface waves into a bright network on the seabed (optional).

The model, stated so it can be checked (not fitted to measurements):

- The surface carries WAVES sinusoids of seeded directions, phases and wavelengths around the frame's `wavelength_m`
  (lambda), with rms slope `slope` (s). Rays through the surface point x_s are bent towards the troughs and focus at
  the paraxial focal depth of a wave, F = n / (n - 1) * lambda / (2 pi s) (a wave crest is a lens of curvature
  k^2 A = k s): about 1-5 m for wind waves.
- The pattern on the surface plane is P(x) = (FLOOR + exp(-(G(x) / LINE_WIDTH)^2)) / mean, G = sum_i a_i cos(k_i .
  x + phi_i), sum a_i^2 = 1: bright curves along the zero set of the wave field (the network where neighbouring
  lenses' light meets) over a dimmer floor, divided by its mean over the plane (measured per frame on a grid many
  wavelengths wide, to under 1%), so caustics move light around and add none.
- A point at depth d below the surface sees the pattern where the refracted sun ray through it left the surface,
  x_s = p_xy + sun_xy * d / sun_z, with contrast m(d) = (1 - exp(-d / F)) * exp(-(k theta d)^2 / 8): it builds up
  towards the focal depth and is blurred by the sun's angular radius in water (theta; k the mean wavenumber), and
  C = 1 + m(d) (P(x_s) - 1) multiplies the sun's *unscattered* share, exp(-c d / mu), which scattering already
  removes with depth: in turbid or deep water caustics vanish by themselves.
- Not modelled: light shafts in the water (in-scattering of the focused beam), the wave field's evolution between
  frames, dispersion. The path tracer's flat surface has no caustics, so the fidelity bench runs with them off.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from seasynth.worker.light import WATER_INDEX

WAVES = 5
LINE_WIDTH = 0.2  # of the caustic curves, in units of the wave field G (whose standard deviation is 0.71)
FLOOR = 0.3  # the pattern's level between the curves, before normalising (curves peak at 1 + FLOOR)
_MEAN_GRID = 256  # points a side of the grid that measures the pattern's mean, over _MEAN_SPAN longest wavelengths
_MEAN_SPAN = 32
SUN_RADIUS_RAD = math.radians(0.2666) / WATER_INDEX  # the sun's angular radius under the surface (paraxial)
_WAVELENGTH_SPREAD = (0.6, 1.0)  # each wave's wavelength is the frame's lambda times a draw in this range


@dataclass(frozen=True)
class Caustics:
    """One frame's wave field: wavenumber vectors k (WAVES, 2) rad/m in the world xy plane, phases (WAVES,), amplitudes
    a (WAVES,) with sum a^2 = 1, and the derived focal depth (m), blur rate (1/m^2) and pattern normaliser (1 / the
    pattern's mean before normalising)."""

    k: np.ndarray
    phase: np.ndarray
    amplitude: np.ndarray
    focal_depth_m: float
    blur_per_m2: float  # (k theta)^2 / 8: contrast falls as exp(-blur_per_m2 d^2)
    norm: float

    def record(self) -> dict:
        return {"wavenumbers_rad_per_m": self.k.tolist(), "phases_rad": self.phase.tolist(),
                "amplitudes": self.amplitude.tolist(), "line_width": LINE_WIDTH, "floor": FLOOR,
                "focal_depth_m": self.focal_depth_m, "blur_per_m2": self.blur_per_m2}


def sample_caustics(rng: np.random.Generator, wavelength_m: float, slope: float) -> Caustics:
    """The frame's waves, drawn in a fixed order from rng (the frame's own caustics stream)."""
    angles = rng.uniform(0.0, 2.0 * math.pi, WAVES)
    lengths = wavelength_m * rng.uniform(*_WAVELENGTH_SPREAD, WAVES)
    phase = rng.uniform(0.0, 2.0 * math.pi, WAVES)
    k = (2.0 * math.pi / lengths)[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    amplitude = np.full(WAVES, 1.0 / math.sqrt(WAVES))
    k_mean = 2.0 * math.pi / float(np.mean(lengths))
    focal = WATER_INDEX / (WATER_INDEX - 1.0) * wavelength_m / (2.0 * math.pi * slope)
    c = Caustics(k=k, phase=phase, amplitude=amplitude, focal_depth_m=focal,
                 blur_per_m2=(k_mean * SUN_RADIUS_RAD) ** 2 / 8.0, norm=1.0)
    side = np.linspace(0.0, _MEAN_SPAN * float(lengths.max()), _MEAN_GRID, endpoint=False)
    grid = np.stack(np.meshgrid(side, side), axis=-1)
    return dataclasses.replace(c, norm=1.0 / float(pattern(c, grid).mean()))


def contrast(c: Caustics, depth_m: np.ndarray) -> np.ndarray:
    """m(d) in [0, 1) for depths below the surface (metres, >= 0); any shape, float64."""
    d = np.maximum(np.asarray(depth_m, dtype=np.float64), 0.0)
    return -np.expm1(-d / c.focal_depth_m) * np.exp(-c.blur_per_m2 * d * d)


def pattern(c: Caustics, xy: np.ndarray) -> np.ndarray:
    """P at surface points xy (..., 2) world metres: mean 1 over the plane, > 0. float64, shape (...)."""
    g = np.cos(np.asarray(xy, dtype=np.float64) @ c.k.T + c.phase) @ c.amplitude
    return (FLOOR + np.exp(-((g / LINE_WIDTH) ** 2))) * c.norm


def factor(c: Caustics, points_world: np.ndarray, surface_z: float, sun_dir_world: np.ndarray) -> np.ndarray:
    """C = 1 + m(d) (P(x_s) - 1) at world points (..., 3) below the surface; the numpy twin of the shader's."""
    p = np.asarray(points_world, dtype=np.float64)
    d = np.maximum(surface_z - p[..., 2], 0.0)
    s = np.asarray(sun_dir_world, dtype=np.float64)
    xs = p[..., :2] + s[:2] * (d / s[2])[..., None]
    return 1.0 + contrast(c, d) * (pattern(c, xs) - 1.0)


# GLSL 330 (inside the surface shader): needs u_caustic_* uniforms and the world position of the shaded point.
# Wavenumbers and phases go in cycles (k / 2 pi, phi / 2 pi) so the shader reduces each argument to [0, 1) with fract
# before cos: GLSL leaves cos's precision at large arguments (100+ radians at far points) to the implementation.
GLSL = f"""
uniform vec2 u_caustic_k[{WAVES}];       // cycles per metre
uniform float u_caustic_phase[{WAVES}];  // cycles
uniform float u_caustic_amp[{WAVES}];
uniform float u_caustic_norm;
uniform float u_caustic_focal;
uniform float u_caustic_blur;
uniform vec3 u_sun_world;
float caustic_factor(vec3 p_world, float depth) {{
    vec2 xs = p_world.xy + u_sun_world.xy * (depth / u_sun_world.z);
    float g = 0.0;
    for (int i = 0; i < {WAVES}; ++i)
        g += u_caustic_amp[i] * cos(6.283185307179586 * fract(dot(u_caustic_k[i], xs) + u_caustic_phase[i]));
    float m = (1.0 - exp(-depth / u_caustic_focal)) * exp(-u_caustic_blur * depth * depth);
    float r = g / {LINE_WIDTH!r};
    return 1.0 + m * (({FLOOR!r} + exp(-r * r)) * u_caustic_norm - 1.0);
}}
"""
UNIFORMS = ("u_caustic_norm", "u_caustic_focal", "u_caustic_blur",
            *(f"u_caustic_{what}[{i}]" for what in ("k", "phase", "amp") for i in range(WAVES)))
