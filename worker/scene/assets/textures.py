"""Seeded procedural PBR texture sets (albedo factor, normal map, relief) that tile seamlessly, cached per process.

Each family is built from periodic pieces only: white noise shaped in the Fourier domain (numpy's FFT; the
filters' frequencies are whole cycles per tile) and Worley cells on a jittered grid that wraps at the image
border. The fields see only IEEE-exact arithmetic (+ - * /, sqrt, floor, comparisons; no exp, sin or pow whose
last bit may follow numpy's SIMD dispatch), so the bytes follow from numpy's random streams, its FFT and the
sRGB tables of seasynth.worker.frame.srgb; identity is tested across processes on one machine.

Feature sizes are physical (cycles per tile of `tile_m`): `size` sets the resolution, not the pattern's scale.
Timing (uncached, best of 3, pinned to one core of a shared 2-core "Intel Xeon Processor" container under load
~2.6, numpy 2.4.6): a 512 set takes 0.10-0.28 s by family (seaweed, clam and sand fastest; rock and stone
slowest), all nine 1.8 s; a 2048 rock set about 10 s.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from seasynth.worker.frame.srgb import SRGB8_TO_LINEAR, encode_srgb8
from seasynth.worker.scene.assets.procedural import stable_seed

__all__ = ["FAMILIES", "TILE_M", "TextureSet", "normal_map", "texture_set"]

FAMILIES = ("sand", "pebbles", "rock", "mud", "urchin", "coral", "seaweed", "clam", "stone")
# The physical size each family is designed for: about 1 m for seabeds, about 0.2 m for assets.
TILE_M = {"sand": 1.0, "pebbles": 1.0, "rock": 1.0, "mud": 1.0,
          "urchin": 0.2, "coral": 0.2, "seaweed": 0.2, "clam": 0.2, "stone": 0.2}
BASE_LINEAR = 0.4  # the linear code value of albedo factor 1: factors up to 2.5 fit below code 255
MAX_FACTOR = 1.0 / BASE_LINEAR

Filter = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True, eq=False)
class TextureSet:
    """One seeded texture set; `n` is `size`. Equality and hashing go by `key`, which names the content."""

    key: str  # e.g. "texture/sand/3/size=512"
    albedo: np.ndarray  # (n, n, 3) uint8 sRGB codes, read-only, periodic in both axes
    albedo_gain: float  # albedo factor = albedo_gain * srgb_decode(albedo), linear; its mean is 1 per channel
    normal: np.ndarray  # (n, n, 3) uint8 tangent-space normals, (v + 1) / 2 * 255; x right, y up the image, z out
    height_m: np.ndarray  # (n, n) float32 metres, zero mean: the relief `normal` was derived from
    tile_m: float  # metres the tile spans: the normal map's slopes are for this size
    source: str  # e.g. "procedural:sand#3"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, TextureSet) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)


# ---------------------------------------------------------------------------------------------
# Periodic building blocks: (n, n) float64 fields
# ---------------------------------------------------------------------------------------------


def shaped(field: np.ndarray, amplitude: Filter) -> np.ndarray:
    """`field: (n, n)` filtered by `amplitude(kx, ky)` (cycles per tile, rfft2 layout); circular, so periodic."""
    n = field.shape[0]
    ky = np.fft.fftfreq(n, 1.0 / n)[:, None]
    kx = np.fft.rfftfreq(n, 1.0 / n)[None, :]
    return np.fft.irfft2(np.fft.rfft2(field) * amplitude(kx, ky), s=field.shape)


def spectral(rng: np.random.Generator, n: int, amplitude: Filter) -> np.ndarray:
    """Periodic Gaussian noise with the amplitude spectrum `amplitude`; zero mean, unit std."""
    field = shaped(rng.standard_normal((n, n)), amplitude)
    field -= field.mean()
    return field / max(float(field.std()), 1e-300)


def lowpass(kc: float) -> Filter:
    """Amplitude 1 / (1 + (k / kc)^2)^2: smooth features down to about 1 / kc of the tile (a k^-4 tail: a
    gentler one leaves pixel-scale roughness in slopes and warps)."""
    def amplitude(kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        a = 1.0 / (1.0 + (kx * kx + ky * ky) / (kc * kc))
        return a * a
    return amplitude


def band(k0: float, width: float) -> Filter:
    """Amplitude peaked on the ring |k| = k0 (cycles per tile), about `width` wide."""
    return lambda kx, ky: 1.0 / (1.0 + ((np.sqrt(kx * kx + ky * ky) - k0) / width) ** 2)


def fractal(k_lo: float) -> Filter:
    """Amplitude (k_lo^2 + k^2)^-3/4: a rough fractal surface above k_lo cycles per tile."""
    def amplitude(kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        q = np.sqrt(np.sqrt(k_lo * k_lo + kx * kx + ky * ky))
        return 1.0 / (q * q * q)
    return amplitude


def streaks(across: float, along: float) -> Filter:
    """Anisotropic low-pass: features about 1 / across of the tile wide and 1 / along long, along the image's y."""
    return lambda kx, ky: 1.0 / (1.0 + (kx / across) ** 2 + (ky / along) ** 2)


def ripples(d: np.ndarray, k0: float, w_along: float, w_across: float) -> Filter:
    """Narrow band around the wave vectors +-k0 * d (d: (2,) unit, image x and y): parallel crests."""
    def amplitude(kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        k_par = np.abs(kx * d[0] + ky * d[1])
        k_perp = kx * d[1] - ky * d[0]
        a = 1.0 / (1.0 + ((k_par - k0) / w_along) ** 2 + (k_perp / w_across) ** 2)
        return a * a
    return amplitude


def grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates as fractions of the tile: y (n, 1) down the rows, x (1, n) across the columns."""
    t = (np.arange(n) + 0.5) / n
    return t[:, None], t[None, :]


class Cells(NamedTuple):
    """Worley cells at each pixel, all (n, n), in cell units."""

    f1: np.ndarray  # float64 distance to the nearest seed
    edge: np.ndarray  # float64 distance to the border with the second-nearest seed's cell
    owner: np.ndarray  # int64 flat index (row * g + col) of the nearest seed's cell
    dy: np.ndarray  # float64 offset from the pixel to the nearest seed, along y (rows)
    dx: np.ndarray  # float64 the same along x (columns)


def cells(rng: np.random.Generator, y: np.ndarray, x: np.ndarray, g: int, jitter: float,
          stagger: bool = False) -> Cells:
    """Periodic Worley cells: one seed point in each cell of a g x g grid that wraps every g cells.

    y, x: (n, n) or broadcastable, positions in cell units (a periodic warp keeps them periodic).
    jitter: 0 puts each seed at its cell's centre, 1 anywhere in it. stagger (g even): odd rows shifted half a
    cell, a hexagonal-ish lattice. Neighbours are searched 3 x 3 cells around each pixel.
    """
    pts = (1.0 - jitter) / 2.0 + jitter * rng.random((g, g, 2))
    if stagger:
        pts[1::2, :, 1] += 0.5
    y, x = np.broadcast_arrays(y, x)
    cy, cx = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    d1, d2 = np.full(y.shape, np.inf), np.full(y.shape, np.inf)
    y1, x1, y2, x2 = (np.zeros(y.shape) for _ in range(4))
    owner = np.zeros(y.shape, np.int64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            iy, ix = (cy + dy) % g, (cx + dx) % g
            oy = cy + dy + pts[iy, ix, 0] - y
            ox = cx + dx + pts[iy, ix, 1] - x
            d = oy * oy + ox * ox
            first, second = d < d1, (d >= d1) & (d < d2)
            d2 = np.where(first, d1, np.where(second, d, d2))
            y2 = np.where(first, y1, np.where(second, oy, y2))
            x2 = np.where(first, x1, np.where(second, ox, x2))
            d1 = np.where(first, d, d1)
            y1, x1 = np.where(first, oy, y1), np.where(first, ox, x1)
            owner = np.where(first, iy * g + ix, owner)
    # Distance to the perpendicular bisector of the two nearest seeds: the cell border's true distance.
    edge = (d2 - d1) / (2.0 * np.sqrt((y2 - y1) ** 2 + (x2 - x1) ** 2))
    return Cells(np.sqrt(d1), edge, owner, y1, x1)


def triangle(u: np.ndarray) -> np.ndarray:
    """Periodic ramp 0 at whole numbers, 1 half-way between, smoothed (smoothstep): stripes without sin."""
    t = np.abs(u - np.floor(u) - 0.5) * 2.0
    t = 1.0 - t
    return t * t * (3.0 - 2.0 * t)


def rgb(tone: np.ndarray, tint: np.ndarray) -> np.ndarray:
    """Albedo factor (n, n, 3): grey `tone: (n, n)` times `tint: (3,) or (n, n, 3)`."""
    return tone[..., None] * tint


# ---------------------------------------------------------------------------------------------
# Families: (rng, n) -> height_m (n, n) float64 metres, albedo factor (n, n, 3) float64 (mean ~1, normalised later)
# ---------------------------------------------------------------------------------------------


def sand(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Grain speckle over small ripple marks (7-12 cm apart, mm high) with heavier, darker grains in the troughs."""
    d = rng.standard_normal(2)
    r = spectral(rng, n, ripples(d / np.sqrt(d[0] * d[0] + d[1] * d[1]), rng.uniform(8.0, 13.0), 1.0, 1.5))
    r = r + 0.25 * (r * r - 1.0)  # sharp crests, broad flat troughs
    swell = spectral(rng, n, lowpass(2.0))
    grain = spectral(rng, n, lowpass(220.0))
    height = rng.uniform(0.8e-3, 2.0e-3) * r + 1.5e-3 * swell + 0.08e-3 * grain
    speck = rng.random((n, n))
    tone = (1.0 + 0.06 * spectral(rng, n, lowpass(6.0)) - 0.05 * r + 0.06 * grain
            + 0.07 * rng.standard_normal((n, n)) - 0.35 * (speck < 0.01) + 0.35 * (speck > 0.995))
    tint = 1.0 + 0.03 * spectral(rng, n, lowpass(4.0))[..., None] * np.array([1.0, 0.3, -0.8])
    return height, rgb(tone, tint)


def pebbles(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rounded, a little elongated pebbles (3-5 cm, up to ~1 cm high, each its own tone) on darker grit."""
    g = int(rng.integers(20, 32))
    k = g * g
    y, x = grid(n)
    c = cells(rng, y * g, x * g, g, 0.6)
    axis = rng.standard_normal((k, 2))
    axis = (axis / np.sqrt((axis * axis).sum(axis=1, keepdims=True)))[c.owner]
    stretch = rng.uniform(1.0, 1.5, k)[c.owner]
    along = (c.dy * axis[..., 0] + c.dx * axis[..., 1]) / stretch
    across = (c.dy * axis[..., 1] - c.dx * axis[..., 0]) * stretch
    inside = rng.uniform(0.42, 0.6, k)[c.owner] - np.sqrt(along * along + across * across)  # to the rim
    gap = c.edge - 0.04  # to the cell border, less a gap
    inward = 0.5 * (inside + gap - np.sqrt((inside - gap) ** 2 + 0.01))  # smooth min: rounded corners
    m = np.clip(inward / 0.25, 0.0, 1.0)
    pebble_h = rng.uniform(4e-3, 10e-3, k)[c.owner] * (1.0 - (1.0 - m) ** 2)
    grit_h = 1.0e-3 + 0.3e-3 * spectral(rng, n, lowpass(150.0))
    on = pebble_h > grit_h
    tone = (1.0 + 0.22 * np.clip(rng.standard_normal(k), -2.0, 2.0)[c.owner]) * (
        1.0 + 0.05 * spectral(rng, n, lowpass(40.0)) + 0.03 * rng.standard_normal((n, n)))
    tint = 1.0 + 0.03 * np.clip(rng.standard_normal((k, 3)), -2.0, 2.0)[c.owner]
    grit = 0.8 + 0.12 * rng.standard_normal((n, n))
    factor = np.where(on[..., None], rgb(tone, tint), grit[..., None])
    return np.maximum(pebble_h, grit_h), factor


# Encrusting organisms on rock: pink coralline algae, white barnacles / tube worms, green turf.
CRUST = np.array([[1.30, 1.00, 1.10], [1.35, 1.35, 1.30], [0.95, 1.15, 0.90]])


def rock_like(rng: np.random.Generator, n: int, crack_cells: int, k_ridge: float, relief_m: float,
              crack_m: float, k_crust: float) -> tuple[np.ndarray, np.ndarray]:
    """Fractal relief with ridges, cracks along warped cell borders, darker crevices and encrusting patches."""
    y, x = grid(n)
    base = spectral(rng, n, fractal(2.0))
    ridge = np.clip(1.0 - np.abs(spectral(rng, n, band(k_ridge, k_ridge))), 0.0, 1.0) ** 2
    warp = 0.1 * spectral(rng, n, lowpass(2.0 * crack_cells))
    c = cells(rng, y * crack_cells + warp, x * crack_cells + warp.T, crack_cells, 1.0)
    open_ = np.clip(spectral(rng, n, lowpass(crack_cells)) + 0.5, 0.0, 1.0)  # not every border cracks
    crack = np.clip(1.0 - c.edge / 0.03, 0.0, 1.0) * open_
    blobs = spectral(rng, n, band(k_crust, 0.5 * k_crust))
    crust = np.clip((blobs - rng.uniform(1.4, 2.0)) / 0.5, 0.0, 1.0)
    height = relief_m * (0.7 * base + 0.5 * ridge) - crack_m * crack + 0.15 * relief_m * crust
    relief = height - shaped(height, lowpass(k_ridge / 2.0))
    cavity = np.clip(-relief / max(float(relief.std()), 1e-300), 0.0, 3.0)
    tone = (1.0 + 0.10 * spectral(rng, n, lowpass(5.0)) - 0.07 * cavity - 0.35 * crack
            + 0.06 * rng.standard_normal((n, n)))
    mineral = 1.0 + 0.04 * spectral(rng, n, lowpass(3.0))[..., None] * np.array([1.0, 0.2, -0.9])
    colour = CRUST[rng.integers(len(CRUST))]
    return height, rgb(tone, mineral) * (1.0 + crust[..., None] * (colour - 1.0))


def rock(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Seabed rock (1 m tile): cm-scale ridges, cracks 10-20 cm apart, patches of encrusting organisms."""
    return rock_like(rng, n, int(rng.integers(5, 10)), 14.0, 6e-3, 6e-3, 40.0)


def stone(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A stone's surface (0.2 m tile): like rock at a finer scale, fewer and finer cracks."""
    return rock_like(rng, n, int(rng.integers(3, 6)), 12.0, 1.0e-3, 0.6e-3, 30.0)


def mud(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth low-contrast mottling with scattered burrow holes (4-9 mm) and their low rims."""
    g = int(rng.integers(9, 14))
    y, x = grid(n)
    f1, _, owner, _, _ = cells(rng, y * g, x * g, g, 0.9)
    k = g * g
    present = (rng.random(k) < 0.45)[owner]
    q = f1 / (rng.uniform(0.004, 0.009, k)[owner] * g)  # radii 4-9 mm (a cell is 1 / g m)
    hole = np.where(present & (q < 1.0), 1.0 - q * q, 0.0)
    t = np.clip((q - 1.0) / 1.5, 0.0, 1.0)
    rim = np.where(present & (q >= 1.0), (1.0 - (2.0 * t - 1.0) ** 2) ** 2, 0.0)
    mottle, fine = spectral(rng, n, lowpass(5.0)), spectral(rng, n, lowpass(40.0))
    height = 2.5e-3 * mottle + 0.2e-3 * fine - 6e-3 * hole + 0.8e-3 * rim
    tone = 1.0 + 0.06 * mottle + 0.04 * fine - 0.45 * np.sqrt(hole) + 0.06 * rim
    tint = 1.0 + 0.03 * spectral(rng, n, lowpass(3.0))[..., None] * np.array([1.0, 0.4, -0.6])
    return height, rgb(tone, tint)


def urchin(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Urchin test: pale primary tubercles (5-7 mm apart, staggered rows) and smaller secondary ones."""
    g = 2 * int(rng.integers(14, 19))
    y, x = grid(n)
    f1, _, owner, _, _ = cells(rng, y * g, x * g, g, 0.2, stagger=True)
    q = np.clip(f1 / rng.uniform(0.26, 0.36, g * g)[owner], 0.0, 1.0)
    bump = (1.0 - q * q) ** 2
    s1, _, owner2, _, _ = cells(rng, y * 2 * g, x * 2 * g, 2 * g, 0.7)
    q2 = np.clip(s1 / rng.uniform(0.15, 0.3, 4 * g * g)[owner2], 0.0, 1.0)
    bump2 = (1.0 - q2 * q2) ** 2 * (bump == 0.0)
    skin = spectral(rng, n, lowpass(80.0))
    height = rng.uniform(0.8e-3, 1.6e-3, g * g)[owner] * bump + 0.25e-3 * bump2 + 0.04e-3 * skin
    tone = 1.0 + 0.30 * bump * bump + 0.10 * bump2 + 0.06 * skin - 0.08 * (q > 0.9) * (q < 1.0)
    return height, rgb(tone, np.ones(3))


def coral(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Coral skeleton: polyp pores (corallites 5-8 mm apart) as dark cups between lighter walls."""
    g = int(rng.integers(26, 40))
    y, x = grid(n)
    warp = 0.15 * spectral(rng, n, lowpass(g / 2.0))
    c = cells(rng, y * g + warp, x * g + warp.T, g, 0.7)
    cup = np.clip((1.0 - c.f1 / rng.uniform(0.3, 0.42, g * g)[c.owner]) / 0.35, 0.0, 1.0)
    cup = cup * cup * (3.0 - 2.0 * cup)
    wall = np.clip(1.0 - c.edge / 0.12, 0.0, 1.0)
    mottle, fine = spectral(rng, n, lowpass(12.0)), spectral(rng, n, lowpass(150.0))
    height = -1.2e-3 * cup + 0.3e-3 * wall + 0.6e-3 * mottle + 0.03e-3 * fine
    tone = 1.0 - 0.35 * cup + 0.08 * wall + 0.06 * mottle + 0.05 * fine
    tint = 1.0 + cup[..., None] * np.array([0.0, -0.06, -0.03])  # polyp tissue a little warmer
    return height, rgb(tone, tint)


def seaweed(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A blade's fibres: streaks along the image's y at two widths, a gentle undulation and pale epiphyte spots."""
    fibre = spectral(rng, n, streaks(150.0, 3.0))
    strand = spectral(rng, n, streaks(25.0, 2.0))
    blade = spectral(rng, n, lowpass(3.0))
    spots = np.clip((spectral(rng, n, band(60.0, 30.0)) - 2.2) / 0.5, 0.0, 1.0)
    height = 0.05e-3 * fibre + 0.12e-3 * strand + 0.8e-3 * blade + 0.05e-3 * spots
    tone = 1.0 + 0.07 * fibre + 0.10 * strand + 0.05 * blade + 0.25 * spots
    tint = 1.0 + 0.025 * spectral(rng, n, streaks(10.0, 2.0))[..., None] * np.array([-0.5, 1.0, -0.8])
    return height, rgb(tone, tint)


def clam(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Shell: fine growth lines (1.4-2.5 mm) along the image's x, grouped in growth bands, faint radial ribs."""
    bands, per_band = int(rng.integers(9, 14)), int(rng.integers(8, 12))
    y, x = grid(n)
    wobble = spectral(rng, n, lowpass(3.0))
    u = y * (bands * per_band) + 1.5 * wobble  # line units: whole lines per tile, so periodic
    line = triangle(u)
    band_index = np.mod(np.floor(u / per_band), bands).astype(np.int64)
    band_z = np.clip(rng.standard_normal(bands), -2.0, 2.0)[band_index]
    rib = triangle(x * int(rng.integers(15, 30)) + 0.3 * wobble.T)
    strength = 0.7 + 0.3 * spectral(rng, n, lowpass(8.0))
    rough = spectral(rng, n, lowpass(150.0))
    height = 0.12e-3 * strength * line + 0.04e-3 * rib + 0.02e-3 * rough + 0.05e-3 * band_z
    tone = 1.0 + 0.05 * band_z + 0.10 * strength * (line - 0.5) + 0.03 * rib + 0.05 * rough
    tint = 1.0 + 0.02 * band_z[..., None] * np.array([1.0, 0.0, -1.0])
    return height, rgb(tone, tint)


GENERATORS: dict[str, Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]] = {
    "sand": sand, "pebbles": pebbles, "rock": rock, "mud": mud, "urchin": urchin,
    "coral": coral, "seaweed": seaweed, "clam": clam, "stone": stone,
}



def normal_map(height_m: np.ndarray, texel_m: float, row_m: float | None = None) -> np.ndarray:
    """Tangent-space normals of `height_m: (h, w)` metres, columns `texel_m` apart and rows `row_m` apart (default
    texel_m): (h, w, 3) uint8, (v + 1) / 2 * 255 rounded; periodic central differences, x towards increasing
    column, y towards decreasing row."""
    h = np.asarray(height_m, np.float64)
    row_m = texel_m if row_m is None else row_m
    hx = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) / (2.0 * texel_m)
    hy = (np.roll(h, 1, axis=0) - np.roll(h, -1, axis=0)) / (2.0 * row_m)
    z = 1.0 / np.sqrt(hx * hx + hy * hy + 1.0)
    v = np.stack([-hx * z, -hy * z, z], axis=-1)
    return np.clip(np.floor((v + 1.0) * 127.5 + 0.5), 0, 255).astype(np.uint8)


def albedo_codes(factor: np.ndarray) -> tuple[np.ndarray, float]:
    """Factor (n, n, 3) -> sRGB codes (n, n, 3) uint8 and the gain that maps their decoded mean back to 1.

    Each channel is scaled to mean 1 and clipped to [0, MAX_FACTOR] (a few rounds), then encoded with factor 1
    at linear BASE_LINEAR."""
    f = np.maximum(factor, 0.0)
    for _ in range(4):
        f = np.clip(f / f.mean(axis=(0, 1)), 0.0, MAX_FACTOR)
    codes = encode_srgb8(f * BASE_LINEAR)
    return codes, float(1.0 / SRGB8_TO_LINEAR[codes].mean())


def read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def texture_set(family: str, variant: int, size: int = 512) -> TextureSet:
    """Variant `variant` (>= 0) of texture `family` at `size` x `size` texels (a power of two, 16..2048);
    byte-identical in every process, cached per process (after the checks: True must not find variant 1)."""
    if family not in GENERATORS:
        raise ValueError(f"texture family must be one of {', '.join(FAMILIES)}; got {family!r}")
    if isinstance(variant, bool) or not isinstance(variant, (int, np.integer)) or variant < 0:
        raise ValueError(f"texture variant must be an integer >= 0, got {variant!r} for family {family!r}")
    if (isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 16 <= size <= 2048
            or size & (size - 1)):
        raise ValueError(f"texture size must be a power of two from 16 to 2048, got {size!r}")
    return _texture_set(family, int(variant), int(size))


@functools.lru_cache(maxsize=64)
def _texture_set(family: str, variant: int, size: int) -> TextureSet:
    rng = np.random.default_rng(np.random.SeedSequence([stable_seed("texture/" + family), variant]))
    height, factor = GENERATORS[family](rng, size)
    height_m = (height - height.mean()).astype(np.float32)
    tile_m = TILE_M[family]
    codes, gain = albedo_codes(factor)
    return TextureSet(key=f"texture/{family}/{variant}/size={size}", albedo=read_only(codes), albedo_gain=gain,
                      normal=read_only(normal_map(height_m, tile_m / size)), height_m=read_only(height_m),
                      tile_m=tile_m, source=f"procedural:{family}#{variant}")
