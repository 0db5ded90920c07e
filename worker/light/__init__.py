"""Physical underwater light: one water description (absorption, scattering, phase function, depth) and the light
terms derived from it (sun and sky through the water column, lamps on the vehicle, scattering along view rays).

Each term has its own module (`sun`, `sky`, `lamps`), a GLSL part for the renderer and a float64 twin in numpy
(`volume`) that the accuracy bench checks the shaders against. `PhysicalLight` is what a frame hands the renderer;
`Terms` says which terms run, so a term a frame does not need costs nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SNELL_CONE_DEG = 48.6  # half angle of Snell's window (n = 1.333): the sky reaches the water only within it
WATER_INDEX = 1.333
GORDON_PATH_FACTOR = 1.0395  # K_d = 1.0395 (a + b_b) / mu_w (Gordon 1989, Monte Carlo over natural waters)


@dataclass(frozen=True)
class Medium:
    """Homogeneous water with a flat surface. Arrays are (3,) float64 per linear RGB channel, 1/m."""

    a: np.ndarray  # absorption
    b: np.ndarray  # scattering
    g: float  # Henyey-Greenstein asymmetry of the phase function
    surface_z: float  # world z of the water surface (the seabed's reference z = 0 lies depth_m below it)

    @property
    def c(self) -> np.ndarray:
        """Beam attenuation a + b: what an unscattered (shadow-casting) beam loses per metre."""
        return self.a + self.b

    @property
    def backscatter_fraction(self) -> float:
        """B = b_b / b of the Henyey-Greenstein phase function: the share scattered into the backward hemisphere."""
        g = float(self.g)
        if abs(g) < 1e-6:
            return 0.5
        return (1.0 - g) / (2.0 * g) * ((1.0 + g) / math.sqrt(1.0 + g * g) - 1.0)

    @property
    def k(self) -> np.ndarray:
        """Diffuse attenuation per metre of the light's slant path, Gordon's 1.0395 (a + b_b) (Limnol. Oceanogr.
        34(8), 1989): forward-scattered light stays in a broad light field (the sun's below a few metres, the sky's,
        a lamp's cone, a seabed seen by the camera), which loses what is absorbed, on paths ~4% longer than the
        beam's, and what is scattered backwards. Never above c: in nearly clear water it is the beam's c."""
        return np.minimum(GORDON_PATH_FACTOR * (self.a + self.backscatter_fraction * self.b), self.c)


@dataclass(frozen=True)
class Lamp:
    """A spot light in the camera frame (KITTI axes, metres)."""

    position_cam: np.ndarray  # (3,) float64
    direction_cam: np.ndarray  # (3,) float64, unit
    cutoff_rad: float  # half angle where the light ends
    beam_rad: float  # half angle of full intensity
    intensity: np.ndarray  # (3,) float64, linear RGB, irradiance units x m^2 per steradian, on the axis


@dataclass(frozen=True)
class Terms:
    """Which light terms a frame renders; recorded in meta."""

    sun: bool  # the sun's light on surfaces and in the water
    sun_shadows: bool  # a shadow map for the sun's unscattered part
    sky: bool  # sky light through Snell's window
    scattering: bool  # in-scattering along view rays (b > 0)
    lamps: int  # lamps rendered (shadowed by their own shadow maps)
    caustics: bool = False  # the sun's unscattered beam focused by surface waves (lighting.caustics)
    # lamps' forward-scattered light spread in angle (lamps.light_factor); off, it stays in the sharp profile. Only
    # where the water keeps enough forward-scattered light for it to matter (lamps.spread_worthwhile).
    lamp_spread: bool = False
    # the sun's and the sky's light along view rays from the solved water column (PhysicalLight.column): single
    # scattering through c, the multiply scattered rest from the column's table at the camera (the `solved` module)
    solved: bool = False

    def names(self) -> list[str]:
        out = ["sun"] * self.sun + ["sun_shadows"] * self.sun_shadows + ["caustics"] * self.caustics
        out += ["sky"] * self.sky
        out += ["scattering"] * self.scattering + [f"lamp{i}" for i in range(self.lamps)]
        return out + ["lamp_spread"] * self.lamp_spread + ["solved_column"] * self.solved


@dataclass(frozen=True)
class PhysicalLight:
    """Everything the renderer needs for the physical model of one frame (world frame z up)."""

    medium: Medium
    sun_dir_world: np.ndarray  # (3,) unit, towards the sun, refracted into the water
    sun_irradiance: np.ndarray  # (3,) just below the surface, normal to the beam (0 when the sun is down)
    sky_irradiance: np.ndarray  # (3,) sky's irradiance on a horizontal surface just below the surface
    lamps: tuple[Lamp, ...]
    terms: Terms
    caustics: object = None  # seasynth.worker.light.caustics.Caustics when terms.caustics
    column: object = None  # seasynth.worker.light.solved.SolvedWater when terms.solved
    seabed_albedo: object = None  # (3,) float64 the seabed's mean albedo (linear), for the solved column's seabed
    seabed_z: float = 0.0  # world z of the seabed's mean plane

    def coefficients(self) -> dict:
        """Every derived coefficient a frame uses, for meta."""
        m = self.medium
        solved = {"solved_column": self.column.record()} if self.terms.solved else {}
        return {
            "a": m.a.tolist(),
            "b": m.b.tolist(),
            "g": m.g,
            "c": m.c.tolist(),
            "K": m.k.tolist(),
            "surface_z": m.surface_z,
            "sun_direction_in_water": self.sun_dir_world.tolist(),
            "sun_irradiance": self.sun_irradiance.tolist(),
            "sky_irradiance": self.sky_irradiance.tolist(),
            "lamps": [
                {
                    "position_cam": lp.position_cam.tolist(),
                    "direction_cam": lp.direction_cam.tolist(),
                    "beam_width_deg": float(np.degrees(lp.beam_rad)),
                    "cutoff_deg": float(np.degrees(lp.cutoff_rad)),
                    "intensity": lp.intensity.tolist(),
                }
                for lp in self.lamps
            ],
            "terms": self.terms.names(),
            "caustics": self.caustics.record() if self.terms.caustics else None,
        } | solved


def hg(cos_theta: np.ndarray, g: float) -> np.ndarray:
    """Henyey-Greenstein phase function (1/sr) of the scattering angle's cosine."""
    denom = np.maximum(1.0 + g * g - 2.0 * g * cos_theta, 1e-12)
    return (1.0 - g * g) / (4.0 * math.pi * denom**1.5)
