"""Jerlov water types: per-metre transmittance, attenuation and default veiling light."""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

JERLOV_TYPES: tuple[str, ...] = ("I", "II", "III", "1C", "3C", "5C", "7C", "9C")
"""Known Jerlov water types: oceanic I-III (clearest first), then coastal 1C-9C (clearest first)."""

# Per-metre transmittance N (fraction of light left after 1 m), linear (R, G, B).
# The table stores N, not beta: beta = -ln N.  Each N is exp(-beta) rounded to 4 decimals,
# with beta the approximate values of the reference table (I: 0.10, 0.04, 0.018 1/m, ...),
# so -ln N reproduces them to 1e-4 1/m.  1C is not in the reference table; its betas
# (0.31, 0.15, 0.16) are chosen between III and 3C.
_TRANSMITTANCE: dict[str, tuple[float, float, float]] = {
    "I": (0.9048, 0.9608, 0.9822),
    "II": (0.8025, 0.9231, 0.9418),
    "III": (0.7483, 0.8869, 0.8869),
    "1C": (0.7334, 0.8607, 0.8521),
    "3C": (0.7118, 0.8187, 0.8025),
    "5C": (0.6703, 0.7261, 0.6703),
    "7C": (0.6188, 0.6126, 0.5886),
    "9C": (0.5488, 0.4584, 0.2894),
}

# Default veiling light B_inf, linear RGB (R, G, B) in [0, 1].  Plausible choices, not
# measurements: oceanic water is blue, brighter for the clearer types (III is close to the
# reference "deep blue" (0, 0, 0.064)); coastal water shifts to green (3C is the reference
# "green coastal" (0.007, 0.147, 0.233)) and towards yellow-green for the most turbid types.
_VEILING_LIGHT: dict[str, tuple[float, float, float]] = {
    "I": (0.001, 0.020, 0.110),
    "II": (0.001, 0.016, 0.090),
    "III": (0.001, 0.012, 0.075),
    "1C": (0.004, 0.080, 0.170),
    "3C": (0.007, 0.147, 0.233),
    "5C": (0.012, 0.160, 0.190),
    "7C": (0.020, 0.150, 0.130),
    "9C": (0.030, 0.130, 0.070),
}

# Marine snow (aggregates of diameter >= 0.5 mm, the usual definition) per cubic metre, the default range of
# water.particles.density_per_m3 for each type. Chosen, not measured: in-situ camera counts of marine snow span
# from under one to tens of aggregates per litre (the review of Alldredge & Silver, Progress in Oceanography
# 20:41-82, 1988), fewest in clear open ocean and most in productive coastal water; the ranges rise with the
# types' turbidity (their particle scattering b) within that span.
_MARINE_SNOW: dict[str, tuple[float, float]] = {
    "I": (20.0, 100.0),
    "II": (100.0, 500.0),
    "III": (300.0, 1000.0),
    "1C": (200.0, 1000.0),
    "3C": (500.0, 2000.0),
    "5C": (1000.0, 3000.0),
    "7C": (2000.0, 5000.0),
    "9C": (3000.0, 8000.0),
}
MARINE_SNOW_PER_M3: MappingProxyType[str, tuple[float, float]] = MappingProxyType(_MARINE_SNOW)
"""Read-only: type name -> default marine snow density range (min, max), particles >= 0.5 mm per m^3."""

JERLOV_TRANSMITTANCE: MappingProxyType[str, tuple[float, float, float]] = MappingProxyType(_TRANSMITTANCE)
"""Read-only: type name -> per-metre transmittance N, (R, G, B), dimensionless in (0, 1)."""

JERLOV_VEILING_LIGHT: MappingProxyType[str, tuple[float, float, float]] = MappingProxyType(_VEILING_LIGHT)
"""Read-only: type name -> default veiling light B_inf, linear (R, G, B) in [0, 1]."""


def _check_name(name: str) -> str:
    if not isinstance(name, str) or name not in _TRANSMITTANCE:
        raise ValueError(f"unknown Jerlov water type {name!r}; known types: {', '.join(JERLOV_TYPES)}")
    return name


def jerlov_transmittance(name: str) -> np.ndarray:
    """Per-metre transmittance N of water type `name`: (3,) float64, (R, G, B), in (0, 1)."""
    return np.array(_TRANSMITTANCE[_check_name(name)], dtype=np.float64)


def jerlov_beta(name: str) -> np.ndarray:
    """Attenuation coefficient beta = -ln N of water type `name`: (3,) float64, 1/m, (R, G, B)."""
    return -np.log(jerlov_transmittance(name))


def jerlov_veiling_light(name: str) -> np.ndarray:
    """Default veiling light B_inf of water type `name`: (3,) float64, linear RGB in [0, 1]."""
    return np.array(_VEILING_LIGHT[_check_name(name)], dtype=np.float64)


# Inherent optical properties of the Jerlov types: absorption a and scattering b (1/m), linear (R, G, B) as band
# averages over R 600-650 nm, G 525-550 nm, B 450-475 nm of the 25 nm tables of Solonenko & Mobley, "Inherent
# optical properties of Jerlov water types", Applied Optics 54(17):5392 (2015), Tables 3-8. Their 5C rows at
# 600-700 nm repeat the 300-400 nm rows (a defect of the published table); 5C's red uses Williamson & Hollins,
# Applied Optics 61:9951 (2022) instead. Type I's red absorption is pure water's (Pope & Fry 1997). b was obtained
# there by inverting K_d, so it is the least certain number; a + (1 - g) b with g = 0.92 stays within about 25% of
# Jerlov's K_d for every type and channel.
_IOP: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "I": ((0.288, 0.054, 0.0185), (0.00105, 0.00187, 0.00343)),
    "II": ((0.288, 0.0546, 0.0234), (0.289, 0.372, 0.482)),
    "III": ((0.290, 0.0577, 0.0362), (0.790, 1.02, 1.32)),
    "1C": ((0.297, 0.072, 0.091), (0.293, 0.380, 0.491)),
    "3C": ((0.300, 0.080, 0.130), (0.857, 1.10, 1.43)),
    "5C": ((0.320, 0.122, 0.251), (1.07, 1.39, 1.79)),
    "7C": ((0.359, 0.214, 0.465), (1.90, 2.45, 3.15)),
    "9C": ((0.429, 0.389, 0.826), (2.51, 3.25, 4.20)),
}


def jerlov_absorption(name: str) -> np.ndarray:
    """Absorption a of water type `name`: (3,) float64, 1/m, (R, G, B)."""
    return np.array(_IOP[_check_name(name)][0], dtype=np.float64)


def jerlov_scattering(name: str) -> np.ndarray:
    """Scattering b of water type `name`: (3,) float64, 1/m, (R, G, B)."""
    return np.array(_IOP[_check_name(name)][1], dtype=np.float64)
