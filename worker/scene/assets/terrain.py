"""Seabed terrains: procedural heightfields (sand, pebbles, rock), height lookup and image textures."""

from __future__ import annotations

import functools
import hashlib
import io
import operator
from dataclasses import dataclass

import numpy as np
import trimesh

from seasynth.worker.render import Material
from seasynth.worker.scene.assets import AssetError, freeze
from seasynth.worker.scene.assets.geometry import srgb_u8
from seasynth.worker.scene.assets.procedural import stable_seed

STYLES = ("sand", "pebbles", "rock")
LATTICE = 256  # value-noise lattice period, in lattice cells


@dataclass(frozen=True, eq=False)
class Terrain:
    """A seabed mesh (metres, +z up, faces wound so normals point +z) and its height lookup.

    Equality and hashing go by `key`, which names everything the content depends on. The mesh is
    shared through per-process caches: its arrays are read-only.
    """

    key: str
    mesh: trimesh.Trimesh  # vertex colours: (n, 4) uint8 sRGB-encoded RGBA
    heights: np.ndarray | None  # (cells + 1, cells + 1) float32 metres, heights[iy, ix]; None for user meshes
    extent: tuple[float, float, float, float]  # (xmin, xmax, ymin, ymax) metres
    lookup: np.ndarray  # (ny, nx) float64 metres on a regular grid spanning `extent`; what height_at reads
    sha256: str | None = None  # hex digest of the source mesh file; None for procedural terrains
    material: Material | None = None  # per-pixel textures (with_material); None: vertex colours only
    tile_m: float | None = None  # metres one repeat of the material's textures spans
    uv_warp: bool = True  # its texture coordinates warped against visible tiling (terrain.anti_tiling)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Surface height (..., ) float64 metres at `xy: (..., 2)` metres; see `bilinear`."""
        return bilinear(self.lookup, self.extent, xy)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Terrain) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)


def bilinear(grid: np.ndarray, extent: tuple[float, float, float, float], xy: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of `grid: (ny, nx)` (grid[iy, ix], corners on `extent`) at `xy: (..., 2)`.

    Points outside `extent` take the value at the nearest edge (all of them, where the extent has no width: a
    terrain.size_m of 5e-324 halves to 0). Returns (...,) float64.
    """
    xy = np.asarray(xy, dtype=np.float64)
    xmin, xmax, ymin, ymax = extent
    ny, nx = grid.shape
    fx = _grid_coordinate(xy[..., 0], xmin, xmax, nx)
    fy = _grid_coordinate(xy[..., 1], ymin, ymax, ny)
    ix = np.minimum(fx.astype(np.int64), nx - 2)
    iy = np.minimum(fy.astype(np.int64), ny - 2)
    tx, ty = fx - ix, fy - iy
    g = grid.astype(np.float64, copy=False)
    bottom = g[iy, ix] * (1 - tx) + g[iy, ix + 1] * tx
    top = g[iy + 1, ix] * (1 - tx) + g[iy + 1, ix + 1] * tx
    return bottom * (1 - ty) + top * ty


def _grid_coordinate(v: np.ndarray, lo: float, hi: float, n: int) -> np.ndarray:
    """(...,) float64: where v lies on n grid points spanning [lo, hi], in grid steps, clipped to the grid."""
    if not hi > lo:
        return np.zeros(np.shape(v))
    with np.errstate(over="ignore"):  # a tiny span: far points overflow to +-inf, which the clip takes to an edge
        return np.clip((v - lo) / (hi - lo) * (n - 1), 0.0, n - 1)


def grid_faces(nx: int, ny: int) -> np.ndarray:
    """Faces (2 (nx-1)(ny-1), 3) int64 of a vertex grid `iy * nx + ix`; normals +z when x, y grow with ix, iy."""
    ix, iy = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (iy * nx + ix).ravel()
    b, c, d = a + 1, a + nx + 1, a + nx
    return np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], axis=1).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
# Noise (free functions; every call draws its own lattice from `rng`)
# ---------------------------------------------------------------------------------------------


def value_noise(rng: np.random.Generator, xy: np.ndarray, frequency: float) -> np.ndarray:
    """Smooth value noise in [-1, 1] at `xy: (n, 2)` metres with features `1 / frequency` metres apart; (n,)."""
    lattice = rng.uniform(-1.0, 1.0, (LATTICE, LATTICE))
    p = xy * frequency + rng.uniform(0.0, LATTICE, 2)
    i = np.floor(p).astype(np.int64)
    t = p - i
    t = t * t * (3.0 - 2.0 * t)
    i0, i1 = i % LATTICE, (i + 1) % LATTICE
    bottom = lattice[i0[:, 1], i0[:, 0]] * (1 - t[:, 0]) + lattice[i0[:, 1], i1[:, 0]] * t[:, 0]
    top = lattice[i1[:, 1], i0[:, 0]] * (1 - t[:, 0]) + lattice[i1[:, 1], i1[:, 0]] * t[:, 0]
    return bottom * (1 - t[:, 1]) + top * t[:, 1]


def fbm(rng: np.random.Generator, xy: np.ndarray, frequency: float, octaves: int, gain: float,
        ridged: bool = False) -> np.ndarray:
    """Fractal sum of `octaves` value-noise octaves (frequency doubling, amplitude x `gain`); (n,) float64.

    `ridged` folds each octave (1 - 2|n|) for sharp crests, as in rock.
    """
    total = np.zeros(len(xy))
    amplitude = 1.0
    for octave in range(octaves):  # octaves, not vertices
        n = value_noise(rng, xy, frequency * 2.0**octave)
        total += amplitude * ((1.0 - 2.0 * np.abs(n)) if ridged else n)
        amplitude *= gain
    return total


def octaves_below_nyquist(frequency: float, spacing_m: float, most: int) -> int:
    """How many doubling octaves from `frequency` (1/m) stay below half the grid rate (at least 1, at most `most`).
    A spacing of 0 (terrain.size_m / cells below the smallest float, as size_m 5e-324 gives) resolves every one."""
    if spacing_m <= 0:
        return most
    limit = 0.5 / spacing_m
    return int(np.clip(np.floor(np.log2(limit / frequency)) + 1, 1, most))


# ---------------------------------------------------------------------------------------------
# Styles: each returns large-scale relief (n,) (any scale; stretched to relief_m), fine detail
# (n,) in metres at its physical size, and sRGB colours (n, 3) in [0, 1].
# ---------------------------------------------------------------------------------------------


def sand(rng: np.random.Generator, xy: np.ndarray, spacing_m: float
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Low dunes with ripples 0.5-1.5 cm high, 8-20 cm apart (never under 4 grid cells); pale sand."""
    dunes = fbm(rng, xy, 0.3, octaves_below_nyquist(0.3, spacing_m, 3), 0.4)
    wavelength = max(rng.uniform(0.08, 0.2), 4.0 * spacing_m)
    angle = rng.uniform(0.0, np.pi)
    warp = 1.5 * fbm(rng, xy, 0.8, octaves_below_nyquist(0.8, spacing_m, 2), 0.5)
    along = xy @ np.array([np.cos(angle), np.sin(angle)])
    ripples = np.sin(2.0 * np.pi * along / wavelength + warp)
    detail = rng.uniform(0.0025, 0.0075) * ripples
    base = np.array([0.76, 0.70, 0.53]) * rng.uniform(0.9, 1.08) + rng.normal(0.0, 0.02, 3)
    tone = 1.0 + 0.08 * fbm(rng, xy, 1.5, octaves_below_nyquist(1.5, spacing_m, 3), 0.5) + 0.04 * ripples
    return dunes, detail, base * tone[:, None]


def pebbles(rng: np.random.Generator, xy: np.ndarray, spacing_m: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Round pebbles on a jittered grid (4-8 cm apart, never under 3 grid cells), each its own grey/brown."""
    pitch = max(rng.uniform(0.04, 0.08), 3.0 * spacing_m)
    jitter = rng.uniform(0.15, 0.85, (LATTICE, LATTICE, 2))
    radius = pitch * rng.uniform(0.3, 0.6, (LATTICE, LATTICE)) * (rng.random((LATTICE, LATTICE)) < 0.85)
    palette = np.array([[0.55, 0.54, 0.52], [0.45, 0.40, 0.34], [0.62, 0.58, 0.50], [0.35, 0.33, 0.32],
                        [0.50, 0.42, 0.35]])
    colour = palette[rng.integers(len(palette), size=(LATTICE, LATTICE))] * rng.uniform(
        0.8, 1.15, (LATTICE, LATTICE, 1))
    cell = np.floor(xy / pitch).astype(np.int64)
    best = np.zeros(len(xy))
    best_colour = np.zeros((len(xy), 3))
    for dy in (-1, 0, 1):  # the 9 neighbouring lattice cells, each vectorised over all vertices
        for dx in (-1, 0, 1):
            cx, cy = (cell[:, 0] + dx) % LATTICE, (cell[:, 1] + dy) % LATTICE
            centre = (cell + [dx, dy] + jitter[cy, cx]) * pitch
            r = radius[cy, cx]
            bump = 0.6 * np.sqrt(np.maximum(r * r - np.sum((xy - centre) ** 2, axis=1), 0.0))
            higher = bump > best
            best = np.where(higher, bump, best)
            best_colour[higher] = colour[cy, cx][higher]
    grit = np.array([0.60, 0.55, 0.45]) * (1.0 + 0.1 * fbm(rng, xy, 4.0, octaves_below_nyquist(
        4.0, spacing_m, 3), 0.5))[:, None]
    rgb = np.where((best > 0)[:, None], best_colour, grit)
    undulation = fbm(rng, xy, 0.4, octaves_below_nyquist(0.4, spacing_m, 2), 0.5)
    return undulation, best, rgb


def rock(rng: np.random.Generator, xy: np.ndarray, spacing_m: float
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rough ridged fractal rock down to the grid resolution (all of it scales with relief); dark grey/brown."""
    height = fbm(rng, xy, 0.5, octaves_below_nyquist(0.5, spacing_m, 8), 0.6, ridged=True)
    base = np.array([[0.30, 0.29, 0.28], [0.32, 0.27, 0.22], [0.25, 0.25, 0.26]])[rng.integers(3)]
    tone = 1.0 + 0.18 * fbm(rng, xy, 2.0, octaves_below_nyquist(2.0, spacing_m, 4), 0.6)
    low = (height - height.min()) / max(np.ptp(height), 1e-12)  # crevices darker than crests
    return height, np.zeros(len(xy)), base * (tone * (0.75 + 0.4 * low))[:, None]


STYLE_FUNCTIONS = {"sand": sand, "pebbles": pebbles, "rock": rock}


def heightfield(rng: np.random.Generator, style: str, size_m: float, cells: int, relief_m: float) -> Terrain:
    """Square seabed `size_m` across centred on the origin with `cells` quads a side; lowest point at z = 0.

    `relief_m` is the peak-to-peak height of the style's large-scale shape; fine detail (sand ripples,
    pebbles) is added on top at its physical size, so the total span is relief_m plus a few cm.
    """
    if style not in STYLE_FUNCTIONS:
        raise ValueError(f"unknown terrain style {style!r}; known styles: {', '.join(STYLES)}")
    cells = operator.index(cells)
    if cells < 1 or not size_m > 0 or not relief_m >= 0:
        raise ValueError(f"terrain needs cells >= 1, size_m > 0, relief_m >= 0; got cells={cells}, "
                         f"size_m={size_m}, relief_m={relief_m}")
    size_m, relief_m = float(size_m), float(relief_m)
    half = size_m / 2.0
    axis = np.linspace(-half, half, cells + 1)
    gx, gy = np.meshgrid(axis, axis)  # (cells+1, cells+1), [iy, ix]
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    large, detail, rgb = STYLE_FUNCTIONS[style](rng, xy, size_m / cells)
    span = np.ptp(large)
    z = detail + ((large - large.min()) / span * relief_m if span > 0 else 0.0)
    heights = (z - z.min()).astype(np.float32).reshape(cells + 1, cells + 1)
    heights.flags.writeable = False
    vertices = np.column_stack([xy, heights.ravel().astype(np.float64)])
    colours = srgb_u8(rgb)
    digest = hashlib.sha256(heights.tobytes() + colours.tobytes()).hexdigest()[:16]  # rng state is not nameable
    mesh = trimesh.Trimesh(vertices=vertices, faces=grid_faces(cells + 1, cells + 1), vertex_colors=colours,
                           process=False)
    key = f"terrain/{style}/content={digest}/size={size_m!r}/cells={cells}/relief={relief_m!r}"
    return Terrain(key=key, mesh=freeze(mesh), heights=heights, extent=(-half, half, -half, half),
                   lookup=heights)


@functools.lru_cache(maxsize=32)
def procedural_terrain(style: str, variant: int, size_m: float, cells: int, relief_m: float) -> Terrain:
    """Variant `variant` (>= 0) of a `heightfield` style, identical in every process; cached per process."""
    variant = operator.index(variant)
    if variant < 0:
        raise ValueError(f"terrain variant must be >= 0, got {variant} for style {style!r}")
    rng = np.random.default_rng(np.random.SeedSequence([stable_seed("terrain/" + style), variant]))
    terrain = heightfield(rng, style, size_m, cells, relief_m)
    key = f"terrain/{style}/{variant}/size={float(size_m)!r}/cells={cells}/relief={float(relief_m)!r}"
    return Terrain(key=key, mesh=terrain.mesh, heights=terrain.heights, extent=terrain.extent,
                   lookup=terrain.lookup)


# ---------------------------------------------------------------------------------------------
# Image textures (applied per pixel: seasynth.worker.scene.materials)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Texture:
    """A decoded image texture. Equality and hashing go by `sha256`, which names the content."""

    sha256: str  # hex digest of the image file's bytes
    pixels: np.ndarray  # (h, w, 3) uint8 sRGB, read-only; h, w >= 1
    source: str  # the file it came from, for messages

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Texture) and other.sha256 == self.sha256

    def __hash__(self) -> int:
        return hash(self.sha256)


def decode_texture(data: bytes, source: str) -> Texture:
    """Decode image file bytes (any format Pillow reads) to RGB; `AssetError` naming `source` if unusable."""
    from PIL import Image, UnidentifiedImageError  # the worker extra; only needed for textures

    try:
        with Image.open(io.BytesIO(data)) as image:
            pixels = np.asarray(image.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise AssetError(f"{source}: cannot decode image ({exc})") from exc
    if pixels.size == 0:
        raise AssetError(f"{source}: image is empty")
    pixels.flags.writeable = False
    return Texture(sha256=hashlib.sha256(data).hexdigest(), pixels=pixels, source=source)


@functools.lru_cache(maxsize=64)
def with_material(terrain: Terrain, material: Material | None, key: str, white: bool, tile_m: float,
                  uv_warp: bool = True) -> Terrain:
    """`terrain` drawn with a per-pixel material (seasynth.worker.scene.materials) named by `key`, its texture
    repeating every tile_m metres (its coordinates warped: uv_warp); `white`: its vertex colours set to white, for a material whose base colour is the
    surface's whole colour (a user's texture). Heights, extent and lookup are the terrain's. Cached per process."""
    mesh = terrain.mesh
    if white:
        mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces),
                               vertex_colors=np.full((len(mesh.vertices), 4), 255, np.uint8), process=False)
        mesh = freeze(mesh)
    key = f"{terrain.key}+material/{key}/tile={tile_m!r}" + ("/white" if white else "") + ("" if uv_warp else "/unwarped")
    return Terrain(key=key, mesh=mesh, heights=terrain.heights, extent=terrain.extent, lookup=terrain.lookup,
                   sha256=terrain.sha256, material=material, tile_m=float(tile_m), uv_warp=uv_warp)
