"""Synthetic hazed photos of a known water for the calibration tests, and what every estimate must satisfy."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

from seasynth.service.calibration.estimate import WaterEstimate
from seasynth.service.spec.dataset import DatasetSpec, read_spec_file
from seasynth.worker.frame.formation import haze
from seasynth.worker.frame.srgb import encode_srgb8

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
BETA_D = np.array([0.34, 0.20, 0.22])  # 1/m, Jerlov 3C
BETA_B = 0.9 * BETA_D
B_INF = np.array([0.05, 0.15, 0.23])  # linear; red above 3C's 0.007 so that every channel's backscatter shows


def seabed(h: int = 240, w: int = 320, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A scene that meets the estimator's prior: J (h, w, 3) float64, a 3x3-pixel block texture uniform in [0, 0.6]
    whatever the range; range (h, w) float64 metres, +inf (open water) over the top quarter, then 15 m down to 1 m."""
    rng = np.random.default_rng(seed)
    rows = np.arange(h)[:, None] * np.ones((1, w))
    horizon = h // 4
    z = np.where(rows < horizon, np.inf, 1.0 + 14.0 * ((h - 1 - rows) / (h - 1 - horizon)) ** 2)
    blocks = rng.uniform(0.0, 0.6, (h // 3 + 1, w // 3 + 1, 3))
    return np.repeat(np.repeat(blocks, 3, 0), 3, 1)[:h, :w], z


def photo(sigma: float = 0.0, **kw) -> tuple[np.ndarray, np.ndarray]:
    """(h, w, 3) uint8 sRGB photo of seabed() through the known water, and its range."""
    J, z = seabed(**kw)
    linear = haze(J, z, BETA_D, BETA_B, B_INF, np.float64)
    if sigma:
        linear = linear + np.random.default_rng(5).normal(0.0, sigma, linear.shape)
    return encode_srgb8(linear), z


def rel(got, want) -> np.ndarray:
    return np.abs(np.asarray(got, dtype=float) - want) / want


def assert_no_nan(e: WaterEstimate) -> None:
    """Every number finite, JSON without NaN, and None exactly where a channel is not identified."""
    text = json.dumps(e.as_dict(), allow_nan=False)
    assert text
    for c in (e.beta_D, e.beta_B, e.B_inf, e.beta_D_ratio, e.beta_B_ratio, e.absorption, e.scattering):
        for v, s, ok in zip(c.value, c.sigma, c.identified):
            assert (v is None) == (not ok) and (s is None) == (not ok), c
            if ok:
                assert np.isfinite(v) and np.isfinite(s) and s >= 0, c


def full_spec(water: dict) -> DatasetSpec:
    data = read_spec_file(EXAMPLE)
    data["water"] = json.loads(json.dumps(water))
    return DatasetSpec.model_validate(data)


def bomb_png(width: int, height: int) -> bytes:
    """A few hundred bytes of PNG whose header declares width x height 8-bit RGB pixels."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
