"""Deterministic procedural marine litter: bottles, cans, tyres, rope, net, cinder blocks and pipes."""

from __future__ import annotations

import numpy as np
import trimesh

from seasynth.worker.scene.assets.geometry import (
    finish,
    pick_colour,
    revolve,
    ring_points,
    tubes,
    unit,
    wave_field,
    widened,
)

PLASTIC_PALETTE = np.array([[0.72, 0.82, 0.86], [0.35, 0.60, 0.40], [0.30, 0.50, 0.75],
                            [0.88, 0.88, 0.86], [0.60, 0.40, 0.25]])
LABEL_PALETTE = np.array([[0.80, 0.15, 0.12], [0.15, 0.30, 0.70], [0.95, 0.80, 0.20],
                          [0.90, 0.90, 0.90], [0.20, 0.55, 0.25]])
GLASS_PALETTE = np.array([[0.15, 0.35, 0.15], [0.35, 0.20, 0.08], [0.70, 0.78, 0.72], [0.20, 0.30, 0.45]])
CAN_PALETTE = np.array([[0.75, 0.75, 0.77], [0.75, 0.12, 0.12], [0.15, 0.25, 0.60],
                        [0.20, 0.45, 0.25], [0.80, 0.65, 0.25], [0.10, 0.10, 0.10]])
RUST = np.array([0.45, 0.25, 0.12])
TYRE_PALETTE = np.array([[0.08, 0.08, 0.08], [0.12, 0.11, 0.10], [0.16, 0.16, 0.17]])
ROPE_PALETTE = np.array([[0.90, 0.75, 0.15], [0.90, 0.45, 0.10], [0.20, 0.35, 0.70],
                         [0.25, 0.50, 0.25], [0.85, 0.85, 0.80], [0.12, 0.12, 0.12]])
NET_PALETTE = np.array([[0.25, 0.45, 0.30], [0.20, 0.35, 0.60], [0.85, 0.45, 0.12],
                        [0.10, 0.10, 0.10], [0.80, 0.80, 0.75]])
CONCRETE_PALETTE = np.array([[0.55, 0.54, 0.52], [0.48, 0.47, 0.45], [0.62, 0.60, 0.56]])
PIPE_PALETTE = np.array([[0.55, 0.57, 0.58], [0.80, 0.40, 0.15], [0.85, 0.85, 0.82],
                         [0.10, 0.10, 0.10], [0.45, 0.27, 0.15], [0.58, 0.56, 0.53]])


def laid_down(vertices: np.ndarray, rng: np.random.Generator, p: float) -> np.ndarray:
    """`vertices: (n, 3)` of an upright object laid on its side (its +z axis along +x) with probability `p`; a
    rotation, so faces keep their winding."""
    if rng.random() < p:
        return np.column_stack([vertices[:, 2], vertices[:, 1], -vertices[:, 0]])
    return vertices


def crushed(vertices: np.ndarray, rng: np.random.Generator, size: float, most: float) -> np.ndarray:
    """An upright object of height about `size` squashed along y by up to `most` (0: intact) where it is crushed
    hardest, with dents."""
    crush = rng.uniform(0.0, most) if rng.random() < 0.6 else 0.0
    dent = 1.0 + 0.08 * (crush > 0) * wave_field(rng, vertices / size, 12, 4.0)
    squash = 1.0 - crush * np.sin(np.pi * np.clip(vertices[:, 2] / size, 0.0, 1.0)) ** 2
    return vertices * np.column_stack([dent, squash * dent, np.ones(len(vertices))])


def plastic_bottle(rng: np.random.Generator) -> trimesh.Trimesh:
    """Plastic drinks bottle 15-34 cm long (0.33-2 l), capped, with a label band on half of them, intact or crushed,
    mostly lying on its side (828 triangles)."""
    radius = rng.uniform(0.025, 0.045)
    height = radius * rng.uniform(5.5, 7.0) + 0.02
    neck, cap = rng.uniform(0.0125, 0.014), rng.uniform(0.0145, 0.016)
    shoulder = rng.uniform(0.55, 0.7) * height
    r = np.array([0.55 * radius, 0.95 * radius, radius, radius, 0.94 * radius, radius, radius, 0.75 * radius,
                  neck, neck, cap, cap, 0.8 * cap])
    z = np.array([0.0, 0.004, 0.02, 0.3 * height, 0.32 * height, 0.34 * height, shoulder,
                  0.5 * (shoulder + height - 0.045), height - 0.045, height - 0.022, height - 0.022, height - 0.002,
                  height])
    vertices, faces = revolve(r, z, 32)
    colour = pick_colour(rng, PLASTIC_PALETTE, 0.1)
    label = pick_colour(rng, LABEL_PALETTE, 0.15) if rng.random() < 0.5 else colour
    band = (vertices[:, 2] > 0.34 * height) & (vertices[:, 2] < 0.95 * shoulder)
    rgb = np.where(band[:, None], label, colour)
    rgb = np.where((vertices[:, 2] > height - 0.022)[:, None], pick_colour(rng, LABEL_PALETTE, 0.1), rgb)
    return finish(laid_down(crushed(vertices, rng, height, 0.6), rng, 0.85), faces, rgb)


def glass_bottle(rng: np.random.Generator) -> trimesh.Trimesh:
    """Glass bottle 19-34 cm long (beer to wine), a long neck with a lip ring, mostly lying on its side (636
    triangles)."""
    radius = rng.uniform(0.028, 0.04)
    height = rng.uniform(0.19, 0.34)
    neck = rng.uniform(0.012, 0.015)
    shoulder = rng.uniform(0.5, 0.62) * height
    r = np.array([0.6 * radius, 0.9 * radius, radius, radius, 0.7 * radius, neck * 1.15, neck, neck + 0.003,
                  neck + 0.003, 0.75 * neck])
    z = np.array([0.006, 0.0, 0.012, shoulder, shoulder + 0.12 * height, 0.78 * height, height - 0.016,
                  height - 0.014, height - 0.002, height])
    vertices, faces = revolve(r, z, 32)
    colour = pick_colour(rng, GLASS_PALETTE, 0.1)
    film = 1.0 + 0.08 * wave_field(rng, vertices * 20.0, 12, 1.0)
    return finish(laid_down(vertices, rng, 0.85), faces, colour * film[:, None])


def can(rng: np.random.Generator) -> trimesh.Trimesh:
    """Drinks can 9-17 cm long (5.3-6.6 cm across), domed base and necked top, intact or crushed, rusting on a
    third of them, mostly lying on its side (572 triangles)."""
    radius = rng.uniform(0.0265, 0.033)
    height = rng.uniform(0.093, 0.168)
    r = radius * np.array([0.55, 0.8, 0.97, 1.0, 1.0, 0.86, 0.87, 0.87, 0.8])
    z = np.array([0.008, 0.0, 0.004, 0.012, height - 0.014, height - 0.004, height - 0.001, height,
                  height - 0.003])
    vertices, faces = revolve(r, z, 32)
    vertices = crushed(vertices, rng, height, 0.7)
    colour = pick_colour(rng, CAN_PALETTE, 0.1)
    rust = rng.uniform(0.0, 1.0) * (rng.random() < 0.35)
    patch = np.clip(wave_field(rng, vertices / 0.03, 12, 1.0) - 1.0 + rust, 0.0, 1.0)[:, None]
    rgb = (1 - patch) * colour + patch * RUST
    return finish(laid_down(vertices, rng, 0.75), faces, rgb)


def tyre(rng: np.random.Generator) -> trimesh.Trimesh:
    """Car or van tyre 55-83 cm across and 15-30 cm wide without its wheel, a block tread on its crown, lying flat
    or on its edge (2.4k triangles)."""
    outer = rng.uniform(0.275, 0.4)
    inner = outer * rng.uniform(0.55, 0.7)
    width = rng.uniform(0.15, 0.3)
    psi = 2.0 * np.pi * np.arange(20) / 20  # the cross-section, counter-clockwise in (r, z)
    c, s = np.cos(psi), np.sin(psi)
    r = 0.5 * (outer + inner) + 0.5 * (outer - inner) * np.sign(c) * np.abs(c) ** 0.5
    z = 0.5 * width * np.sign(s) * np.abs(s) ** 0.5
    sides = 60
    vertices, faces = revolve(r, z, sides, closed=True)
    crown = np.repeat(c > 0.8, sides) & (np.tile(np.arange(sides), 20) % 4 < 2)
    vertices = widened(vertices, 1.0 + crown * rng.uniform(0.008, 0.015) / outer)
    if rng.random() < 0.4:  # on its edge
        vertices = np.column_stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]])
    colour = pick_colour(rng, TYRE_PALETTE, 0.1)
    return finish(vertices, faces, colour * (1.0 + 0.15 * wave_field(rng, vertices * 8.0, 12, 1.0))[:, None])


def rope(rng: np.random.Generator) -> trimesh.Trimesh:
    """A fragment of three-strand rope 30-120 cm long (15-125 cm across) and 1.2-3 cm thick, lying in gentle curves on
    the seabed (316-1260 triangles)."""
    length = rng.uniform(0.3, 1.2)
    radius = rng.uniform(0.006, 0.015)
    sections, sides = max(int(length / 0.015), 12), 8
    s = np.linspace(0.0, 1.0, sections)
    heading = rng.uniform(0.0, 2.0 * np.pi) + np.cumsum(rng.normal(0.0, 1.0, sections)) * 0.25 / np.sqrt(sections)
    heading += rng.uniform(-1.5, 1.5) * np.sin(np.pi * rng.uniform(0.5, 2.0) * s)
    step = length / (sections - 1)
    centre = np.column_stack([np.cumsum(step * np.cos(heading)), np.cumsum(step * np.sin(heading)),
                              radius * (1.0 + 0.8 * np.sin(2.0 * np.pi * rng.uniform(0.5, 2.0) * s) ** 2)])
    axis = unit(np.gradient(centre, axis=0))
    offsets = ring_points(centre, axis, np.ones(sections), sides) - centre[:, None]  # (sections, sides, 3) unit
    theta = 2.0 * np.pi * np.arange(sides) / sides
    lay = 2.0 * np.pi * length * s / (rng.uniform(3.0, 4.0) * 2.0 * radius)  # one turn every 3-4 diameters
    strands = radius * (1.0 + 0.15 * np.cos(3.0 * theta[None] - lay[:, None]))
    vertices, faces = tubes((centre[:, None] + strands[..., None] * offsets)[None])
    colour = pick_colour(rng, ROPE_PALETTE, 0.15)
    fouled = 1.0 + 0.12 * wave_field(rng, vertices * 10.0, 12, 1.0) - 0.1 * np.cos(3.0 * theta - lay[:, None]).ravel()
    return finish(vertices, faces, colour * fouled[:, None])


def net(rng: np.random.Generator) -> trimesh.Trimesh:
    """A torn fragment of fishing net 18-110 cm across, draped over the seabed's bumps: 8-12 strands each way,
    3-9 cm apart and 2-5 mm thick, each a closed tube (<= 2.2k triangles)."""
    n = int(rng.integers(8, 13))
    mesh = rng.uniform(0.03, 0.09)
    radius = rng.uniform(0.001, 0.0025)
    grid = (np.arange(n) - 0.5 * (n - 1)) * mesh
    knots = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1) + rng.normal(0.0, 0.1 * mesh, (n, n, 2))
    extent = 0.5 * (n - 1) * mesh
    bumps = rng.uniform(-extent, extent, (int(rng.integers(1, 4)), 2))
    spread = rng.uniform(0.3, 0.6) * extent
    d2 = ((knots[:, :, None] - bumps) ** 2).sum(-1) / (spread * spread)
    lift = rng.uniform(0.1, 0.4) * spread * np.exp(-d2).max(-1)  # slopes under about 0.6
    points = np.concatenate([knots, (lift + radius)[..., None]], -1)  # (n, n, 3)
    rows = np.concatenate([points, points.transpose(1, 0, 2)])  # (2n, n, 3): strands along y, then along x
    axis = unit(np.gradient(rows, axis=1).reshape(-1, 3))
    rings = ring_points(rows.reshape(-1, 3), axis, np.full(2 * n * n, radius), 4).reshape(2 * n, n, 4, 3)
    torn = rng.random((2 * n, n - 1)) < 0.08  # strand pieces broken off: each strand keeps its longest run
    keep = []
    for k in range(2 * n):  # per strand (<= 24)
        runs = np.split(np.arange(n), np.flatnonzero(torn[k]) + 1)
        keep.append(max(runs, key=len))
    vertices, faces = zip(*(tubes(rings[k, run][None]) for k, run in enumerate(keep) if len(run) > 1))
    offsets = np.cumsum([0] + [len(v) for v in vertices[:-1]])
    colour = pick_colour(rng, NET_PALETTE, 0.15)
    vertices = np.concatenate(vertices)
    return finish(vertices, np.concatenate([f + o for f, o in zip(faces, offsets)]),
                  colour * (1.0 + 0.1 * wave_field(rng, vertices * 10.0, 12, 1.0))[:, None])


def slab_faces(solid: np.ndarray, layers: int) -> np.ndarray:
    """Outward faces (F, 3) of the prism over the cells `solid: (nx, ny) bool` of a grid, vertex `(i * (ny + 1) + j)
    * layers + l` at grid node (i, j) (x, y increasing) on layer l (0 the bottom face, layers - 1 the top); its walls
    are cut at every layer, so their shading bends only near the edges."""
    nx, ny = solid.shape

    def node(i: np.ndarray, j: np.ndarray, layer: int) -> np.ndarray:
        return (i * (ny + 1) + j) * layers + layer

    i, j = np.nonzero(solid)
    top = layers - 1
    quads = [np.stack([node(i, j, top), node(i + 1, j, top), node(i + 1, j + 1, top), node(i, j + 1, top)], -1),
             np.stack([node(i, j, 0), node(i, j + 1, 0), node(i + 1, j + 1, 0), node(i + 1, j, 0)], -1)]
    padded = np.pad(solid, 1)
    for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):  # a wall where a solid cell meets an empty one
        i, j = np.nonzero(solid & ~padded[1 + di : nx + 1 + di, 1 + dj : ny + 1 + dj])
        # the cell's edge on that side, counter-clockwise seen from outside
        a = {(1, 0): (i + 1, j), (-1, 0): (i, j + 1), (0, 1): (i + 1, j + 1), (0, -1): (i, j)}[(di, dj)]
        b = {(1, 0): (i + 1, j + 1), (-1, 0): (i, j), (0, 1): (i, j + 1), (0, -1): (i + 1, j)}[(di, dj)]
        quads += [np.stack([node(*a, k), node(*b, k), node(*b, k + 1), node(*a, k + 1)], -1) for k in range(top)]
    q = np.concatenate(quads)
    return np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


def cinder_block(rng: np.random.Generator) -> trimesh.Trimesh:
    """Concrete cinder block 39-44 cm long, 19-22 cm high and 14-22 cm wide with two or three hollow cores, weathered
    and chipped, standing or on its side (900-1224 triangles)."""
    length, high, wide = rng.uniform(0.39, 0.44), rng.uniform(0.19, 0.215), rng.uniform(0.14, 0.215)
    cores = int(rng.integers(2, 4))
    shell, web = rng.uniform(0.025, 0.035), rng.uniform(0.025, 0.04)
    core = (length - 2 * shell - (cores - 1) * web) / cores
    xs = np.cumsum([0.0, shell] + [core, web] * (cores - 1) + [core, shell])
    ys = np.array([0.0, shell, wide - shell, wide])
    cells = np.ones((len(xs) - 1, 3), bool)
    cells[1:-1:2, 1] = False  # the cores
    split = 3  # each cell cut in 3 x 3, so chips and wear have vertices to move
    xs = np.interp(np.arange(split * (len(xs) - 1) + 1) / split, np.arange(len(xs)), xs)
    ys = np.interp(np.arange(split * 3 + 1) / split, np.arange(4), ys)
    solid = np.repeat(np.repeat(cells, split, 0), split, 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = np.array([0.0, 0.01, high - 0.01, high])
    vertices = np.stack([np.repeat(gx.ravel(), len(z)), np.repeat(gy.ravel(), len(z)), np.tile(z, gx.size)], -1)
    faces = slab_faces(solid, len(z))
    used = np.unique(faces)  # nodes inside the faces have no wall: their middle layers are unused
    vertices, faces = vertices[used], np.searchsorted(used, faces)
    wear = 0.002 * wave_field(rng, vertices * 30.0, 12, 1.0)[:, None] * rng.normal(1.0, 0.3, (len(vertices), 3))
    rim = np.minimum(np.minimum(vertices[:, 0], length - vertices[:, 0]),
                     np.minimum(vertices[:, 1], wide - vertices[:, 1])) < 1e-9
    chip = rim[:, None] * rng.uniform(0.0, 0.004, (len(vertices), 3)) * np.sign([0.5 * length, 0.5 * wide, 0.5 * high]
                                                                               - vertices)
    vertices = vertices + wear + chip
    if rng.random() < 0.35:  # on its side: the cores run horizontally
        vertices = np.column_stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]])
    colour = pick_colour(rng, CONCRETE_PALETTE, 0.1)
    return finish(vertices, faces, colour * (1.0 + 0.1 * wave_field(rng, vertices * 15.0, 12, 1.0))[:, None])


def pipe(rng: np.random.Generator) -> trimesh.Trimesh:
    """A pipe segment 20-120 cm long and 4-30 cm across with open ends and a wall 4-12% of its diameter (PVC,
    HDPE, steel or concrete), lying on its side (576 triangles)."""
    length = rng.uniform(0.2, 1.2)
    outer = 0.5 * rng.uniform(0.04, 0.3)
    inner = outer * (1.0 - 2.0 * rng.uniform(0.04, 0.12))
    bevel = 0.1 * (outer - inner)
    r = np.array([inner + bevel, outer - bevel, outer, outer, outer - bevel, inner + bevel, inner, inner])
    z = np.array([0.0, 0.0, bevel, length - bevel, length, length, length - bevel, bevel])
    sides = 36
    vertices, faces = revolve(r, z, sides, closed=True)
    vertices = np.column_stack([vertices[:, 2], vertices[:, 1], -vertices[:, 0]])
    colour = pick_colour(rng, PIPE_PALETTE, 0.1)
    fouled = 1.0 + 0.12 * wave_field(rng, vertices * 8.0, 12, 1.0)
    inside = np.repeat(np.arange(8) >= 6, sides)  # the bore
    return finish(vertices, faces, colour * (fouled * np.where(inside, 0.6, 1.0))[:, None])
