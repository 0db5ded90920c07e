"""The FLS's Cartesian fan image (nearest polar cell per pixel) and its labels: polar and fan boxes per target.

Fan image: apex at the bottom centre, forward up, starboard right, square pixels of ds = range_max / height metres;
pixel (row i, column j) has its centre at x = (j - (W - 1) / 2) ds (starboard), y = (height - 1 - i + 0.5) ds
(forward). A pixel shows the polar cell (floor((r - range_min) / dr), nearest beam) of its centre, 0 outside the fan.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from seasynth.service.spec.sensors import FLS


@dataclass(frozen=True)
class Fan:
    height: int
    width: int
    ds: float  # metres per pixel
    bin: np.ndarray  # (height, width) int64, polar row of each pixel (valid where `inside`)
    beam: np.ndarray  # (height, width) int64, polar column of each pixel
    inside: np.ndarray  # (height, width) bool


@functools.lru_cache(maxsize=8)
def fan_geometry(fls: FLS) -> Fan:
    """The fan image's lookup of FLS.fan_size pixels (at most MAX_FLS_FAN_PIXELS: seasynth.service.spec.sensors)."""
    rmin, rmax = fls.range_m
    dr = (rmax - rmin) / fls.range_bins
    width, height = fls.fan_size()
    ds = rmax / height
    half = math.radians(fls.horizontal_aperture_deg) / 2
    x = (np.arange(width) - (width - 1) / 2) * ds
    y = (height - 1 - np.arange(height) + 0.5) * ds
    X, Y = np.meshgrid(x, y)
    r, az = np.hypot(X, Y), np.arctan2(X, Y)
    spacing = 2 * half / fls.beams
    b = np.floor((r - rmin) / dr).astype(np.int64)
    beam = np.clip(np.rint((az + half) / spacing - 0.5), 0, fls.beams - 1).astype(np.int64)
    inside = (b >= 0) & (b < fls.range_bins) & (np.abs(az) <= half)
    return Fan(height=height, width=width, ds=ds, bin=np.where(inside, b, 0), beam=beam, inside=inside)


def fan_image(polar: np.ndarray, fan: Fan) -> np.ndarray:
    """(fan.height, fan.width) of polar's dtype: polar (range_bins, beams) looked up per pixel, 0 outside the fan."""
    return np.where(fan.inside, polar[fan.bin, fan.beam], 0).astype(polar.dtype)


def fan_box(cells: np.ndarray, fls: FLS, fan: Fan) -> tuple[int, int, int, int]:
    """Inclusive (left, top, right, bottom) fan pixels holding every annular sector of cells (k, 2) int64 (bin,
    beam), clipped to the image: each pixel whose centre's cell is one of them lies inside."""
    rmin, rmax = fls.range_m
    dr = (rmax - rmin) / fls.range_bins
    half = math.radians(fls.horizontal_aperture_deg) / 2
    spacing = 2 * half / fls.beams
    r_lo, r_hi = rmin + cells[:, 0] * dr, rmin + (cells[:, 0] + 1) * dr
    a_lo, a_hi = -half + cells[:, 1] * spacing, -half + (cells[:, 1] + 1) * spacing
    # A beam's cell reaches half a spacing either side of its centre: nearest-beam lookup.
    rs = np.concatenate([r_lo, r_lo, r_hi, r_hi])
    az = np.concatenate([a_lo, a_hi, a_lo, a_hi])
    xs, ys = rs * np.sin(az), rs * np.cos(az)
    straight = (a_lo <= 0) & (a_hi >= 0)  # the arc's forward-most point lies inside the sector
    ys = np.concatenate([ys, r_hi[straight]])
    xs = np.concatenate([xs, np.zeros(int(straight.sum()))])
    cols = xs / fan.ds + (fan.width - 1) / 2
    rows = fan.height - 0.5 - ys / fan.ds
    left, right = int(np.floor(cols.min() + 0.5)), int(np.floor(cols.max() + 0.5))
    top, bottom = int(np.floor(rows.min() + 0.5)), int(np.floor(rows.max() + 0.5))
    return (max(left, 0), max(top, 0), min(right, fan.width - 1), min(bottom, fan.height - 1))


def label_records(cell_of: dict[int, np.ndarray], objects: dict[int, tuple[str, str | None]], fls: FLS,
                  fan: Fan) -> list[dict]:
    """One record per target instance with cells, in id order: class, polar box (inclusive bins and beams), fan box
    (inclusive pixels), cell count, range (m) and bearing (deg) spans of its cells. objects: id -> (role, class)."""
    rmin, rmax = fls.range_m
    dr = (rmax - rmin) / fls.range_bins
    half = fls.horizontal_aperture_deg / 2
    spacing = fls.horizontal_aperture_deg / fls.beams
    out = []
    for iid in sorted(cell_of):
        role, cls = objects.get(iid, ("distractor", None))
        if role != "target":
            continue
        c = cell_of[iid]
        b0, b1, m0, m1 = int(c[:, 0].min()), int(c[:, 0].max()), int(c[:, 1].min()), int(c[:, 1].max())
        out.append({
            "instance_id": iid,
            "class": cls,
            "polar_box": {"bin_min": b0, "beam_min": m0, "bin_max": b1, "beam_max": m1},
            "fan_box": dict(zip(("left", "top", "right", "bottom"), fan_box(c, fls, fan))),
            "cells": int(len(c)),
            "range_m": [rmin + b0 * dr, rmin + (b1 + 1) * dr],
            "bearing_deg": [-half + (m0 + 0.5) * spacing, -half + (m1 + 0.5) * spacing],
        })
    return out
