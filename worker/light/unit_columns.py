"""The water column's unit solves (`column.solve`) that the renderer's solved water reads (`solved`, `seabed`): per
channel, at c = 1, the sun's column, the sky's and the seabed's, for the water's single scattering albedo b / c, g and
the sun's cosine rounded to OMEGA_STEP, G_STEP, MU_STEP (so a frame is the same function of its spec whichever frames
a process rendered before). Each is seeded, kept per process and stored in the folder processes share
(`disk_cache.share_in`), so a process reads what another solved.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
from pathlib import Path

import numpy as np

from seasynth import service
from seasynth.worker.light import GORDON_PATH_FACTOR, Medium
from seasynth.worker.light.column import GRID_PHI, GRID_THETA, Column, phase_kernel, solve
from seasynth.worker.scene.disk_cache import load_npz, shared_folder, store_npz, stored_once

OMEGA_STEP, G_STEP, MU_STEP = 0.005, 0.01, 0.05
PHOTONS = 20000  # per unit column (one channel, sun or sky)
SEED = 20261129
DEPTHS_K = 12.0  # each unit column reaches this many diffuse lengths 1 / K; the last 4 only feed the ones above
NODES_THETA, NODES_PHI = 19, 10  # the view table: polar angle 0..180 by 10 degrees, azimuth to the sun 0..180 by 20


def diffuse_rate(omega: float, g: float) -> float:
    """K / c of `Medium.k` for a water of single scattering albedo omega (at least 0.02: the column's depth scale)."""
    m = Medium(a=np.array([1.0 - omega]), b=np.array([omega]), g=g, surface_z=0.0)
    return max(float(GORDON_PATH_FACTOR * (1.0 - omega + m.backscatter_fraction * omega)), 0.02)


@functools.lru_cache(maxsize=96)
def unit_column(omega: float, g: float, mu_sun: float | None) -> Column:
    """One channel's column at c = 1: the sun's (unit irradiance normal to the beam at cosine mu_sun) or, mu_sun None,
    the sky's (unit radiance in Snell's window), its `j` on the view table's nodes ((nz, NODES_THETA, NODES_PHI)
    float32 box means of the view grid's, `coarse`). Seeded, so a pure function of its arguments; kept per process,
    and read from the folder the process shares what it builds in (disk_cache.share_in), where one was stored."""
    return _stored(("column", omega, g, mu_sun), lambda: _solved(omega, g, mu_sun, node_kernel(g)))


def full_column(omega: float, g: float, mu_sun: float | None) -> Column:
    """unit_column's solve (the same photons) with `j` on the whole view grid (`column.GRID_THETA`, `GRID_PHI`), for
    the column's own path radiance (`column.path_radiance`); neither kept nor stored."""
    return _solved(omega, g, mu_sun, None)


@functools.lru_cache(maxsize=8)
def node_kernel(g: float) -> np.ndarray:
    """(BINS_THETA * BINS_PHI, NODES_THETA * NODES_PHI) the phase kernel to the view grid, box-averaged to the view
    table's nodes (`coarse` of every column of `column.phase_kernel`)."""
    full = phase_kernel(float(g))
    out = coarse(full.reshape(-1, GRID_THETA, GRID_PHI)).reshape(full.shape[0], -1)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=32)
def seabed_column(omega: float, g: float, upwelling: bool = False) -> Column:
    """One channel's seabed column at c = 1, upside down: a plane of unit exitance (its `z` the height above the
    plane, its directions' polar angles from straight down) under water that reaches far above it; the light it
    sends up, scattered once or more, is its `j`, photons coming back to the plane are absorbed there. The plane is
    Lambertian, or with `upwelling` it sends light as deep open water sends it up (`upwelling_shape`). Kept and
    stored as unit_column."""
    z_max = DEPTHS_K / diffuse_rate(omega, g)
    rng = np.random.default_rng([SEED, round(omega / OMEGA_STEP), round(g / G_STEP), 998 + upwelling])
    return _stored(("seabed", omega, g, upwelling), lambda: _on_nodes(solve(
        1.0 - omega, omega, g, 1.0, 0.0, 1.0 / math.pi, z_max, rng, PHOTONS, cone_deg=90.0, sky_single=True,
        sky_shape=upwelling_shape(omega, g) if upwelling else None, kernel=node_kernel(g))))


def reliable_depth(col: Column, kappa: float) -> float:
    """The deepest optical depth of a unit column (or height of a seabed column) whose layers are reliable: the
    last DEPTHS_K - 8 diffuse lengths only feed the ones above. kappa: diffuse_rate of its water."""
    return float(col.z[-1] - (DEPTHS_K - 8.0) / kappa)


def upwelling_shape(omega: float, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(mu (10,) ascending, radiance (10,)) of the light going up in deep open water by the cosine of its angle to
    the vertical, relative: the sky's column's J looking down over its last reliable diffuse length (azimuth mean),
    as the path radiance J / (1 + kappa mu) of a ray looking down into water whose J falls at the diffuse rate."""
    col = unit_column(omega, g, None)
    kappa = diffuse_rate(omega, g)
    reliable = reliable_depth(col, kappa)
    deep = (col.z > reliable - 1.0 / kappa) & (col.z <= reliable)
    j = col.j[deep].mean(axis=(0, -1), dtype=np.float64)[(NODES_THETA - 1) // 2:]  # polar 90..180: looking down
    mu = np.cos(np.radians(np.linspace(90.0, 180.0, len(j)))) * -1.0  # 0..1: the light's angle to the vertical
    return mu, np.maximum(j, 0.0) / (1.0 + kappa * mu)


def _stored(what: tuple, build) -> Column:
    folder = shared_folder()
    if folder is None:
        return build()
    key = repr((service.__version__, *what, PHOTONS, SEED, DEPTHS_K))
    path = folder / f"column-{hashlib.sha256(key.encode()).hexdigest()[:32]}.npz"
    return stored_once(path, _load_column, build, lambda p, col: store_npz(
        p, {f.name: np.asarray(getattr(col, f.name)) for f in dataclasses.fields(Column)}))


def _load_column(path: Path) -> Column | None:
    """The column stored at path; None where there is none or it cannot be read whole (then it is solved again)."""
    return load_npz(path, lambda a: Column(**{f.name: (a[f.name].item() if a[f.name].ndim == 0 else a[f.name])
                                              for f in dataclasses.fields(Column)}))


def _solved(omega: float, g: float, mu_sun: float | None, kernel: np.ndarray | None) -> Column:
    z_max = DEPTHS_K / diffuse_rate(omega, g)
    rng = np.random.default_rng([SEED, round(omega / OMEGA_STEP), round(g / G_STEP), 0 if mu_sun is None
                                 else 1 + round(mu_sun / MU_STEP)])
    if mu_sun is None:
        col = solve(1.0 - omega, omega, g, 1.0, 0.0, 1.0, z_max, rng, PHOTONS, kernel=kernel)
    else:
        col = solve(1.0 - omega, omega, g, mu_sun, 1.0, 0.0, z_max, rng, PHOTONS, kernel=kernel)
    return col if kernel is None else _on_nodes(col)


def _on_nodes(col: Column) -> Column:
    """A column solved with node_kernel, its j shaped (nz, NODES_THETA, NODES_PHI) and kept in float32."""
    return dataclasses.replace(col, j=col.j.reshape(len(col.z), NODES_THETA, NODES_PHI).astype(np.float32))


def quantised(medium: Medium, mu_sun: float) -> list[tuple[float, float, float]]:
    """Per channel the (omega, g, mu_sun) its unit columns are solved for."""
    c = medium.c
    omega = np.where(c > 0, medium.b / np.where(c > 0, c, 1.0), 0.0)
    q = lambda v, s: round(round(float(v) / s) * s, 6)
    return [(q(w, OMEGA_STEP), q(medium.g, G_STEP), min(max(q(mu_sun, MU_STEP), MU_STEP), 1.0)) for w in omega]


def coarse(j: np.ndarray) -> np.ndarray:
    """(..., NODES_THETA, NODES_PHI) box means of (..., GRID_THETA, GRID_PHI) grids about every 4th node (2 either
    side, clipped at the grid's ends)."""
    out = np.empty((*j.shape[:-2], NODES_THETA, NODES_PHI))
    for i in range(NODES_THETA):
        rows = j[..., max(4 * i - 2, 0):min(4 * i + 3, GRID_THETA), :].mean(axis=-2)
        for k in range(NODES_PHI):
            out[..., i, k] = rows[..., max(4 * k - 2, 0):min(4 * k + 3, GRID_PHI)].mean(axis=-1)
    return out


@functools.lru_cache(maxsize=32)
def seabed_profile(omega: float, g: float, upwelling: bool) -> np.ndarray:
    """(nz, NODES_THETA) the seabed column's J by height and polar angle from the zenith (the column turned the
    right way up, its azimuths averaged: a seabed sends the same light every way round), kept per process."""
    out = np.ascontiguousarray(seabed_column(omega, g, upwelling).j.mean(axis=-1, dtype=np.float64)[:, ::-1])
    out.flags.writeable = False
    return out
