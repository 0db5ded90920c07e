"""Side-scan sonar (SSS): one ping line per frame (port and starboard slant-range bins), and waterfalls of a track.

The model is the FLS's per-pixel echo (worker.sensors.fls, which states it) with one beam per side instead of a fan:

- Geometry. Per side one perspective render from the sensor's pose looks across track (the sensor's +x starboard,
  -x port) at depressions from -5 to 89 deg below the sensor's horizontal, ANGLE_STEP_DEG or a third of the
  horizontal beam per pixel (the finer), and +-2 horizontal beam widths along track (the sensor's z). First hits
  give shadows; the nadir gap (slant ranges shorter than the altitude) is empty water, hence 0.
- Each pixel's echo is rho cos^n(theta) B_h(along) B_v(depression - depression_deg) dOmega r^-2 10^(-2 alpha r/10),
  spread over its range footprint into slant-range bins [0, range_m) and divided by the beam's solid angle
  sum(B_h B_v dOmega): B_v is cut where the render ends (-5 and 89 deg), so sidelobes past them are lost.
- TVG (folded into the binning at long range and high frequency), gain, speckle Gamma(L, 1/L) and additive
  Normal(0, sigma) clipped at 0, 16-bit codes: as the FLS, from the frame's own SSS stream.
- Row layout (sss/{frame}.png, (1, 2 bins) uint16): port bins far to near, then starboard near to far, so that
  stacking frames' rows (waterfall) gives the usual display with nadir in the middle.
Not modelled: the vehicle's motion during a ping, multipath (surface and seabed), layback of a towfish, refraction.
Stonefish (GPU raster) and HoloOcean (octree) also simulate side-scan sonar; this one shares the FLS's echo model so
both sonars of a frame agree (their models were not compared here).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from seasynth.service.spec.sensors import SSS, SSS_ANGLE_STEP_DEG, SSS_DEPRESSION_SPAN_DEG, Acoustics
from seasynth.worker.render import View
from seasynth.worker.scene.poses import rigid_inverse
from seasynth.worker.sensors.fls import (
    absorption_db_per_m,
    beam_pattern,
    bin_echoes,
    folds_tvg,
    pixel_echoes,
    speckle_and_noise,
    to_uint16,
)

ANGLE_STEP_DEG = SSS_ANGLE_STEP_DEG
DEPRESSION_SPAN_DEG = SSS_DEPRESSION_SPAN_DEG
SIDES = ("port", "starboard")


@dataclass(frozen=True)
class SssGrid:
    """One side's render grid (the same for both sides, mirrored)."""

    K: np.ndarray  # (3, 3) float64
    width: int  # along track
    height: int  # across track (depression)
    dirs: np.ndarray  # (h, w, 3) float32 unit rays in the side view's frame
    weight: np.ndarray  # (h, w) float64: B_h B_v dOmega / Omega_beam (1/sr * sr), 0 outside the rendered span
    centre_deg: float  # the view's axis depression
    edges: np.ndarray  # (range_bins + 1,) float64 slant-range bin edges, metres


@functools.lru_cache(maxsize=8)
def sss_grid(sss: SSS) -> SssGrid:
    w, h, f = sss.render_size()
    lo, hi = DEPRESSION_SPAN_DEG
    centre = (lo + hi) / 2
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    x = ((np.arange(w) - K[0, 2]) / f)[None, :].repeat(h, 0)
    y = ((np.arange(h) - K[1, 2]) / f)[:, None].repeat(w, 1)
    norm = np.sqrt(1 + x * x + y * y)
    along = np.arcsin(x / norm)
    depression = math.radians(centre) + np.arctan(y)
    inside = (depression >= math.radians(lo)) & (depression <= math.radians(hi))
    weight = np.where(inside, beam_pattern(along, math.radians(sss.horizontal_beam_deg), sss.beam_pattern)
                      * beam_pattern(depression - math.radians(sss.depression_deg), math.radians(sss.vertical_beam_deg),
                                     sss.beam_pattern) / (f * f * norm**3), 0.0)
    dirs = (np.stack([x, y, np.ones_like(x)], axis=-1) / norm[..., None]).astype(np.float32)
    return SssGrid(K=K, width=w, height=h, dirs=dirs, weight=weight / weight.sum(), centre_deg=centre,
                   edges=np.linspace(0.0, sss.range_m, sss.range_bins + 1))


def side_pose(world_from_sensor: np.ndarray, side: str, centre_deg: float) -> np.ndarray:
    """(4, 4) world_from_view of one side's render: looking to `side` (sensor -x or +x), centre_deg below the
    sensor's horizontal, image y further down, image x along track."""
    c, s = math.cos(math.radians(centre_deg)), math.sin(math.radians(centre_deg))
    sign = 1.0 if side == "starboard" else -1.0
    fwd = np.array([sign * c, s, 0.0])
    down = np.array([-sign * s, c, 0.0])
    R = np.stack([np.cross(down, fwd), down, fwd], axis=1)
    T = np.eye(4)
    T[:3, :3] = R
    return world_from_sensor @ T


def side_echo(sss: SSS, grid: SssGrid, range_m: np.ndarray, instance: np.ndarray, reflectivity: np.ndarray,
              alpha_db_per_m: float) -> tuple[np.ndarray, dict[int, tuple[int, int]]]:
    """(range_bins,) float64 noiseless intensity of one side after TVG and gain, and instance id -> (first, last)
    slant-range bin its pixel centres fall in. range_m, instance: (h, w) as rendered (float32 m, +inf; uint32)."""
    edges = grid.edges
    fold = folds_tvg(sss.tvg, alpha_db_per_m, edges)
    _, r, ids, half, echo = pixel_echoes(range_m, instance, grid.dirs, grid.weight, edges, reflectivity,
                                         sss.incidence_exponent, alpha_db_per_m, loss=not fold)
    line = bin_echoes(echo, r, half, np.zeros(len(r), np.int64), edges, 1, alpha_db_per_m if fold else None)[:, 0]
    if sss.tvg and not fold:
        rc = (edges[:-1] + edges[1:]) / 2
        line = line * rc * rc * 10 ** (alpha_db_per_m * rc / 5)
    line = line * 10 ** (sss.gain_db / 10)
    bins = np.floor((r - edges[0]) / (edges[1] - edges[0])).astype(np.int64)
    spans = {int(i): (int(bins[ids == i].min()), int(bins[ids == i].max())) for i in np.unique(ids[ids > 0])}
    return line, spans


@dataclass(frozen=True)
class SssFrame:
    row: np.ndarray  # (1, 2 * range_bins) uint16: port far..near, starboard near..far
    labels: list[dict]
    record: dict


def sss_frame(sss: SSS, acoustics: Acoustics, renderer, items: list, world_from_sensor: np.ndarray,
              objects: dict[int, tuple[str, str | None]], depth_m: float, rng: np.random.Generator) -> SssFrame:
    """One ping of both sides. objects: instance id -> (role, class); rng: the frame's SSS stream (speckle for
    all 2 * range_bins cells, then noise)."""
    grid = sss_grid(sss)
    rho = {"target": sss.reflectivity_target, "distractor": sss.reflectivity_distractor}
    reflectivity = np.zeros(max(objects, default=0) + 1)
    reflectivity[0] = sss.reflectivity_seabed
    for iid, (role, _) in objects.items():
        reflectivity[iid] = rho[role]
    alpha = absorption_db_per_m(sss.frequency_khz, acoustics, depth_m)
    n = sss.range_bins
    lines, labels = [], []
    for side in SIDES:
        view = View(K=grid.K, width=grid.width, height=grid.height, near=0.01, far=sss.range_m * 1.01,
                    cam_from_world=rigid_inverse(side_pose(world_from_sensor, side, grid.centre_deg)))
        instance, range_m = renderer.geometry(view, items)
        line, spans = side_echo(sss, grid, range_m, instance, reflectivity, alpha)
        lines.append(line)
        for iid, (b0, b1) in sorted(spans.items()):
            role, cls = objects.get(iid, ("distractor", None))
            if role != "target":
                continue
            cols = (n - 1 - b1, n - 1 - b0) if side == "port" else (n + b0, n + b1)
            labels.append({"instance_id": iid, "class": cls, "side": side, "bin_min": b0, "bin_max": b1,
                           "column_min": cols[0], "column_max": cols[1]})
    clean = np.concatenate([lines[0][::-1], lines[1]])[None, :]
    row = to_uint16(speckle_and_noise(clean, sss, rng))
    record = {"parameters": sss.model_dump(mode="json"), "pose_world_from_sss": world_from_sensor.tolist(),
              "depth_m": depth_m, "alpha_db_per_m": alpha, "render_size": [grid.width, grid.height],
              "nonzero_cells": int(np.count_nonzero(row))}
    return SssFrame(row=row, labels=labels, record=record)


def waterfall(rows: list[np.ndarray]) -> np.ndarray:
    """(frames, 2 * range_bins) uint16: ping rows (each (1, 2 * range_bins)) stacked in frame order, first on top."""
    return np.concatenate(rows, axis=0)
