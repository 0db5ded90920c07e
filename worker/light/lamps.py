"""Lamps on the vehicle: spot lights fixed to the camera. Their profile is the path tracer's (Mitsuba's `spot`):
full intensity within the beam width, falling linearly in angle to 0 at the cutoff."""

from __future__ import annotations

import math

import numpy as np

from service.spec_light import Lamp as LampSpec
from worker.light import Lamp

# Quadrature nodes of the lamp's single-scattering integral along each view ray, in the equiangular variable
# (Kulla & Fajardo 2012), which turns the inverse-square peak near the lamp into a smooth integrand.
BACKSCATTER_NODES = 24
# The integral stops where light has crossed this many diffuse attenuation lengths (exp(-16) = 1e-7): open water.
CUTOFF_OPTICAL_DEPTH = 16.0
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


def profile(lamp: Lamp, cos_angle: np.ndarray) -> np.ndarray:
    """Spot falloff in [0, 1] for the cosine of the angle off the lamp's axis; any shape, float64."""
    ang = np.arccos(np.clip(cos_angle, -1.0, 1.0))
    width = max(lamp.cutoff_rad - lamp.beam_rad, 1e-9)
    return np.where(ang <= lamp.beam_rad, 1.0, np.clip((lamp.cutoff_rad - ang) / width, 0.0, 1.0))
