"""The seabed beyond the tile: rings of growing width around the terrain out to the camera's far clip, so a ray
that points down meets a seabed wherever the water would still let it be seen (no false horizon at the tile's edge).

The innermost ring is the tile's own boundary (its vertices, heights, colours and normals exactly), so the seam is
closed. Outwards each ring lies `d` metres beyond the tile's edge, `d` growing by FAR_GROWTH a ring, with about as
many vertices along a side as make square cells: a far ring is as coarse as it is far. Over the first BLEND_M metres
the heights and colours go from the edge's to the far field's: the tile's mean height plus relief of the tile's
height spread, and its mean colour (linear light) with a tone of the tile's brightness spread, each from value noise
with features 24 m apart. Relief and tone are each one noise field over the plane, seeded by the terrain's key and
shared by every ring (`far_seabed`), so a world point has one value whichever ring holds it and the seabed runs on
without a seam from ring to ring; neighbouring rings share their common loop's vertices (the zipper stitches a fine
loop to a coarse one). Everything is a pure function of the terrain and the reach, so it is cached per process.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import trimesh

from seasynth.worker.frame.srgb import decode_srgb8, encode_srgb8
from seasynth.worker.scene.assets import freeze
from seasynth.worker.scene.assets.procedural import stable_seed
from seasynth.worker.scene.assets.terrain import Terrain, value_noise

FIRST_RING_M = 0.25  # the first ring's distance beyond the edge
FAR_GROWTH = 1.5  # each ring this much farther out than the one before
BLEND_M = 2.0  # metres beyond the edge over which the edge's heights and colours give way to the far field's
RELIEF_WAVELENGTH_M = 24.0  # the far field's relief and tone features are this far apart
MAX_TONE = 0.25  # the far tone's relative spread is the tile's brightness spread, at most this
RELIEF, TONE = 0, 1  # the far field's two noise fields, by their index in its seed sequence


@dataclass(frozen=True, eq=False)
class FarField:
    """The seabed beyond a terrain: `key` names its content (the terrain's key and the reach)."""

    key: str
    mesh: trimesh.Trimesh  # metres, +z up; vertex colours (n, 4) uint8 sRGB-encoded RGBA, as the terrain's
    rings: tuple[int, ...]  # the first vertex of each ring (0: the edge's), then the vertex count


@dataclass(frozen=True, eq=False)
class FarSeabed:
    """What the far field's seabed is made of, read off a terrain: heights `mean_z + spread_z * relief` (metres) and
    linear-light colours `mean_rgb * (1 + tone * tone_noise)`, the noise fields seeded by `seed`."""

    seed: int
    mean_z: float  # metres
    spread_z: float  # metres
    mean_rgb: np.ndarray  # (3,) float64, linear light
    tone: float  # relative


def seabed_of(terrain: Terrain) -> FarSeabed:
    """The far seabed of `terrain`: its mean height and colour, their spreads, and a seed from its key."""
    grid = np.asarray(terrain.lookup, dtype=np.float64)
    linear = decode_srgb8(np.asarray(terrain.mesh.visual.vertex_colors)[:, :3], np.float64)
    luma = linear @ np.array([0.2126, 0.7152, 0.0722])
    return FarSeabed(seed=stable_seed("far-field/" + terrain.key), mean_z=float(grid.mean()),
                     spread_z=float(grid.std()), mean_rgb=linear.mean(axis=0),
                     tone=min(float(luma.std() / max(luma.mean(), 1e-6)), MAX_TONE))


def far_noise(seed: int, field: int, xy: np.ndarray) -> np.ndarray:
    """Noise field `field` (RELIEF or TONE) of the far seabed `seed` at xy (n, 2) metres: (n,) float64 in [-1, 1],
    features RELIEF_WAVELENGTH_M apart. Its lattice comes from its own seed sequence on every call, so a point's
    value depends on (seed, field, point) alone, never on which ring or batch of points asks."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, field]))
    return value_noise(rng, np.asarray(xy, dtype=np.float64), 1.0 / RELIEF_WAVELENGTH_M)


def far_seabed(seabed: FarSeabed, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The far seabed at xy (n, 2) metres: heights (n,) float64 metres and colours (n, 3) float64 linear light
    (unclipped)."""
    z = seabed.mean_z + seabed.spread_z * far_noise(seabed.seed, RELIEF, xy)
    rgb = seabed.mean_rgb * (1.0 + seabed.tone * far_noise(seabed.seed, TONE, xy))[:, None]
    return z, rgb


def ring_distances(reach_m: float) -> np.ndarray:
    """(k,) float64 metres beyond the tile's edge of rings 1.. (ring 0 is the edge), the last one >= reach_m."""
    d = [FIRST_RING_M]
    while d[-1] < reach_m:
        d.append(d[-1] * FAR_GROWTH)
    return np.asarray(d)


def boundary(nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """The grid's boundary loop, counter-clockwise seen from +z from corner (0, 0): (iy, ix) (L, 2) int64 and its
    perimeter parameter u (L,) float64 in [0, 4): side 0 bottom, 1 right, 2 top, 3 left, the fraction along it."""
    ix, iy = np.arange(nx - 1), np.arange(ny - 1)
    idx = np.concatenate([
        np.stack([np.zeros_like(ix), ix], 1),
        np.stack([iy, np.full_like(iy, nx - 1)], 1),
        np.stack([np.full_like(ix, ny - 1), nx - 1 - ix], 1),
        np.stack([ny - 1 - iy, np.zeros_like(iy)], 1),
    ])
    u = np.concatenate([ix / (nx - 1), 1 + iy / (ny - 1), 2 + ix / (nx - 1), 3 + iy / (ny - 1)])
    return idx, u


def ring_points(u: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(n, 2) xy on the rectangle of half sizes `half` (2,) about `centre` (2,) at perimeter parameters u (n,)."""
    side = np.minimum(np.floor(u).astype(np.int64), 3)
    f = u - side
    sx = np.select([side == 0, side == 1, side == 2], [2 * f - 1, np.ones_like(f), 1 - 2 * f], -np.ones_like(f))
    sy = np.select([side == 0, side == 1, side == 2], [-np.ones_like(f), 2 * f - 1, np.ones_like(f)], 1 - 2 * f)
    return centre + np.stack([sx, sy], 1) * half


def ring_parameters(half: np.ndarray, step: float, most: tuple[int, int]) -> np.ndarray:
    """Perimeter parameters (n,) of a ring whose cells are about `step` metres along each side, never more than the
    edge's own `most` (cells along x, along y)."""
    nx = int(np.clip(round(2 * half[0] / step), 1, most[0]))
    ny = int(np.clip(round(2 * half[1] / step), 1, most[1]))
    return np.concatenate([np.arange(nx) / nx, 1 + np.arange(ny) / ny, 2 + np.arange(nx) / nx,
                           3 + np.arange(ny) / ny])


def zipper(a: np.ndarray, b: np.ndarray, offset_a: int, offset_b: int) -> np.ndarray:
    """Triangles (n, 3) joining the closed loop of parameters `a` (inner) to `b` (outer), both ascending from 0,
    wound counter-clockwise seen from +z; vertex indices start at the offsets."""
    la, lb = len(a), len(b)
    a_next = np.append(a[1:], 4.0)
    b_next = np.append(b[1:], 4.0)
    faces = []
    i = j = 0
    while i < la or j < lb:  # a ring's vertices, not pixels: a few hundred steps
        if j >= lb or (i < la and a_next[i] <= b_next[j]):
            faces.append((offset_a + i, offset_b + j % lb, offset_a + (i + 1) % la))
            i += 1
        else:
            faces.append((offset_a + i % la, offset_b + j, offset_b + (j + 1) % lb))
            j += 1
    return np.asarray(faces, dtype=np.int64)


def periodic_interp(u: np.ndarray, u0: np.ndarray, values: np.ndarray) -> np.ndarray:
    """values (L, c) given at ascending parameters u0 (L,) of a loop of period 4, linearly interpolated at u (n,)."""
    uu = np.append(u0, 4.0)
    vv = np.concatenate([values, values[:1]])
    return np.stack([np.interp(u, uu, vv[:, k]) for k in range(vv.shape[1])], 1)


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@functools.lru_cache(maxsize=64)  # every terrain a spec draws (24 by default: 3 styles x 8 variants), 0.24 MB each
def far_field(terrain: Terrain, reach_m: float) -> FarField:
    """The seabed around `terrain` out to `reach_m` metres beyond its edge: a mesh (metres, +z up, normals +z) with
    sRGB vertex colours like the terrain's, whose inner ring is the terrain's boundary."""
    grid = np.asarray(terrain.lookup, dtype=np.float64)
    ny, nx = grid.shape
    xmin, xmax, ymin, ymax = terrain.extent
    centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
    half = np.array([(xmax - xmin) / 2, (ymax - ymin) / 2])
    idx, u0 = boundary(nx, ny)
    edge_xy = ring_points(u0, centre, half)
    edge_z = grid[idx[:, 0], idx[:, 1]]
    colours = np.asarray(terrain.mesh.visual.vertex_colors)[:, :3]
    linear = decode_srgb8(colours, np.float64)
    if terrain.heights is not None:  # a heightfield: its vertices are the grid's, row by row
        vertex = idx[:, 0] * nx + idx[:, 1]
        edge_xy = np.asarray(terrain.mesh.vertices)[vertex, :2]  # the very same coordinates: no crack at the seam
        edge_rgb = linear[vertex]
        edge_normals = np.asarray(terrain.mesh.vertex_normals)[vertex]
    else:  # a user mesh: its boundary is not a grid; the far field starts from its lookup grid's edge
        edge_rgb = np.repeat(linear.mean(axis=0, keepdims=True), len(u0), 0)
        edge_normals = None
    seabed = seabed_of(terrain)
    loops_u, loops_xy, loops_z, loops_rgb = [u0], [edge_xy], [edge_z], [edge_rgb]
    previous = 0.0
    for d in ring_distances(float(reach_m)):
        ring_half = half + d
        u = ring_parameters(ring_half, d - previous, (nx - 1, ny - 1))
        xy = ring_points(u, centre, ring_half)
        w = smoothstep(np.full(len(u), d / BLEND_M))[:, None]
        far_z, far_rgb = far_seabed(seabed, xy)  # every ring evaluates the one field
        near = periodic_interp(u, u0, np.column_stack([edge_z, edge_rgb]))
        loops_u.append(u)
        loops_xy.append(xy)
        loops_z.append((1 - w[:, 0]) * near[:, 0] + w[:, 0] * far_z)
        loops_rgb.append((1 - w) * near[:, 1:] + w * far_rgb)
        previous = d
    offsets = np.cumsum([0] + [len(u) for u in loops_u])
    faces = np.concatenate([zipper(loops_u[k], loops_u[k + 1], offsets[k], offsets[k + 1])
                            for k in range(len(loops_u) - 1)])
    vertices = np.column_stack([np.concatenate(loops_xy), np.concatenate(loops_z)])
    rgb = np.clip(np.concatenate(loops_rgb), 0.0, 1.0)
    colours = np.full((len(vertices), 4), 255, np.uint8)
    colours[:, :3] = encode_srgb8(rgb)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, process=False)
    normals = np.array(mesh.vertex_normals)
    if edge_normals is not None:
        normals[: len(u0)] = edge_normals  # the seam shades as the tile's edge does
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, vertex_normals=normals,
                           process=False)
    return FarField(key=f"{terrain.key}/far-field/reach={float(reach_m)!r}", mesh=freeze(mesh),
                    rings=tuple(int(o) for o in offsets))
