"""Deterministic procedural meshes: the sea urchin and the distractors (rock, coral, seaweed, clam), and the registry
of every procedural kind, with the marine animals (marine.py) and litter (litter.py)."""

from __future__ import annotations

import functools
import operator
import zlib
from collections.abc import Callable

import numpy as np
import trimesh

from seasynth.worker.scene.assets import Asset, freeze, litter, marine
from seasynth.worker.scene.assets.geometry import (
    cones,
    finish,
    hinged_pair,
    perpendicular_frames,
    pick_colour,
    ring_points,
    smoothstep,
    tubes,
    unit,
    valve,
    wave_field,
)


def stable_seed(name: str) -> int:
    """A process-independent 32-bit integer for `name` (CRC-32 of its UTF-8 bytes; never `hash()`)."""
    return zlib.crc32(name.encode("utf-8"))


# ---------------------------------------------------------------------------------------------
# Assets
# ---------------------------------------------------------------------------------------------

URCHIN_PALETTE = np.array([[0.22, 0.07, 0.20], [0.07, 0.05, 0.08], [0.26, 0.15, 0.08],
                           [0.32, 0.09, 0.14], [0.12, 0.10, 0.14]])
ROCK_PALETTE = np.array([[0.45, 0.44, 0.42], [0.38, 0.33, 0.27], [0.52, 0.47, 0.40],
                         [0.30, 0.30, 0.31], [0.42, 0.36, 0.30]])
CORAL_PALETTE = np.array([[0.85, 0.45, 0.35], [0.70, 0.30, 0.45], [0.88, 0.72, 0.48],
                          [0.55, 0.36, 0.60], [0.88, 0.84, 0.76]])
SEAWEED_PALETTE = np.array([[0.33, 0.42, 0.14], [0.40, 0.30, 0.10], [0.18, 0.45, 0.18],
                            [0.45, 0.26, 0.14], [0.25, 0.33, 0.10]])
CLAM_PALETTE = np.array([[0.85, 0.78, 0.65], [0.60, 0.50, 0.40], [0.75, 0.72, 0.70],
                         [0.50, 0.38, 0.30], [0.80, 0.66, 0.55]])


def urchin(rng: np.random.Generator) -> trimesh.Trimesh:
    """Sea urchin: flattened sphere body (radius 2.5-4 cm) with 60-200 thin tapered spines (<= ~3.3k triangles)."""
    radius = rng.uniform(0.025, 0.04)
    flatten = rng.uniform(0.6, 0.8)
    axes = np.array([radius, radius, radius * flatten])
    sphere = trimesh.creation.icosphere(subdivisions=3)  # 642 vertices, 1280 faces, outward
    body = np.asarray(sphere.vertices) * axes
    body_faces = np.asarray(sphere.faces)

    # Fewer spines underneath (none around the mouth): thin candidate directions by height.
    count = int(rng.integers(60, 201))
    d = unit(rng.normal(size=(4 * count, 3)))
    keep_p = np.where(d[:, 2] < -0.85, 0.0, 0.25 + 0.75 * smoothstep(-0.8, 0.2, d[:, 2]))
    d = d[rng.random(len(d)) < keep_p][:count]
    n = len(d)
    on_body = d / np.sqrt(np.sum((d / axes) ** 2, axis=1, keepdims=True))  # ellipsoid point along d
    axis = unit(d + rng.normal(0.0, 0.12, (n, 3)))
    base_r = rng.uniform(0.0008, 0.0014) * rng.uniform(0.8, 1.2, n)  # base diameter ~1.3-3.4 mm
    mean_len = radius * rng.uniform(1.0, 3.0)
    length = mean_len * rng.uniform(0.75, 1.15, n) * (0.35 + 0.65 * smoothstep(-0.6, 0.3, d[:, 2]))
    sides = int(rng.integers(4, 7))
    spine_v, spine_f = cones(on_body - axis * (0.1 * radius), axis, length, base_r, sides)

    colour = pick_colour(rng, URCHIN_PALETTE, 0.25)
    body_rgb = colour * rng.uniform(0.85, 1.15, (len(body), 1))
    tip_tint = np.clip(colour * rng.uniform(1.3, 2.2) + rng.uniform(0.0, 0.08, 3), 0, 1)
    spine_rgb = np.repeat(colour * rng.uniform(0.8, 1.2, (n, 1)), sides + 1, axis=0)
    spine_rgb[sides::sides + 1] = tip_tint
    return finish(np.concatenate([body, spine_v]),
                  np.concatenate([body_faces, spine_f + len(body)]),
                  np.concatenate([body_rgb, spine_rgb]))


def rock(rng: np.random.Generator) -> trimesh.Trimesh:
    """Rock: noise-displaced icosphere 8-40 cm across with a flattened underside (1280 triangles)."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    d = np.asarray(sphere.vertices)
    bumps = 0.7 * wave_field(rng, d, 12, 1.8) + 0.3 * wave_field(rng, d, 24, 5.0)
    r = np.clip(1.0 + rng.uniform(0.08, 0.18) * bumps, 0.6, 1.5)
    size = rng.uniform(0.08, 0.40)
    axes = 0.5 * size * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.35, 0.75)])
    p = d * r[:, None] * axes
    floor = -0.55 * axes[2]  # monotone squash below `floor` keeps the winding outward
    p[:, 2] = np.where(p[:, 2] < floor, floor + 0.25 * (p[:, 2] - floor), p[:, 2])
    colour = pick_colour(rng, ROCK_PALETTE, 0.2)
    shade = 1.0 + 0.12 * wave_field(rng, d, 12, 3.0) + rng.normal(0.0, 0.04, len(d))
    return finish(p, np.asarray(sphere.faces), colour * shade[:, None])


def coral(rng: np.random.Generator) -> trimesh.Trimesh:
    """Branching coral 8-35 cm tall: 4-5 levels of 2-3 tapered hexagonal branches (<= 121 x 20 triangles)."""
    height = rng.uniform(0.08, 0.35)
    levels = int(rng.integers(4, 6))
    start = np.zeros((1, 3))
    direction = unit(np.array([[0.0, 0.0, 1.0]]) + rng.normal(0.0, 0.1, (1, 3)))
    length = np.array([height * 0.22])
    r0 = np.array([height * rng.uniform(0.035, 0.06)])
    starts, ends, radii0, radii1, level_of = [], [], [], [], []
    for level in range(levels):  # loop over tree levels (<= 5), branches within a level are vectorised
        r1 = r0 * 0.72
        starts.append(start), ends.append(start + direction * length[:, None])
        radii0.append(r0), radii1.append(r1), level_of.append(np.full(len(start), level))
        parent = np.repeat(np.arange(len(start)), rng.integers(2, 4, len(start)))
        u, v = perpendicular_frames(direction[parent])
        angle = rng.uniform(0.0, 2.0 * np.pi, len(parent))
        spread = rng.uniform(0.5, 1.1, len(parent))[:, None]
        tilt = spread * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)
        child = unit(direction[parent] + tilt + [0.0, 0.0, 0.35])
        start = ends[-1][parent] - child * (0.5 * r1[parent])[:, None]  # sink into the joint
        direction, length, r0 = child, length[parent] * rng.uniform(0.7, 0.95, len(parent)), r1[parent]
    a, b = np.concatenate(starts), np.concatenate(ends)
    axis = unit(b - a)
    rings = np.stack([ring_points(a, axis, np.concatenate(radii0), 6),
                      ring_points(b, axis, np.concatenate(radii1), 6)], axis=1)
    vertices, faces = tubes(rings)
    colour = pick_colour(rng, CORAL_PALETTE, 0.15)
    tip = np.clip(colour * 1.25 + 0.05, 0, 1)
    t = np.repeat(np.concatenate(level_of) / (levels - 1), 12)[:, None]
    rgb = (1 - t) * colour + t * tip + rng.normal(0.0, 0.02, (len(vertices), 3))
    return finish(vertices, faces, rgb)


def seaweed(rng: np.random.Generator) -> trimesh.Trimesh:
    """Seaweed: 3-6 twisted, bending blades 12-40 cm tall, each a closed 1 mm thick ribbon (<= 6 x 164 triangles)."""
    blades = int(rng.integers(3, 7))
    segments = 20
    s = np.linspace(0.0, 1.0, segments + 1)[None, :]  # (1, S+1) position along the blade
    height = rng.uniform(0.12, 0.40) * rng.uniform(0.7, 1.0, (blades, 1))
    width = rng.uniform(0.01, 0.03) * rng.uniform(0.8, 1.2, (blades, 1))
    base = rng.normal(0.0, 0.012, (blades, 2))
    lean = rng.uniform(0.0, 2.0 * np.pi, (blades, 1))
    bend = rng.uniform(0.1, 0.4, (blades, 1)) * height * s**2
    wiggle = 0.03 * height * np.sin(2 * np.pi * (rng.uniform(1, 2.5, (blades, 1)) * s
                                                 + rng.uniform(0, 1, (blades, 1))))
    centre = np.stack([base[:, :1] + (bend + wiggle) * np.cos(lean),
                       base[:, 1:] + (bend + wiggle) * np.sin(lean),
                       height * s], axis=-1)  # (blades, S+1, 3)
    twist = rng.uniform(0.0, 2 * np.pi, (blades, 1)) + rng.uniform(-2 * np.pi, 2 * np.pi, (blades, 1)) * s
    e1 = np.stack([np.cos(twist), np.sin(twist), np.zeros_like(twist)], axis=-1)
    e2 = np.stack([-np.sin(twist), np.cos(twist), np.zeros_like(twist)], axis=-1)  # e1 x e2 = +z
    half_w = (0.5 * width * (1.0 - 0.75 * s) * (1.0 + 0.1 * np.sin(9.0 * np.pi * s)))[..., None]
    half_t = 0.0005
    corners = np.array([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])  # CCW about +z
    rings = (centre[:, :, None] + corners[:, 0, None] * half_w[:, :, None] * e1[:, :, None]
             + corners[:, 1, None] * half_t * e2[:, :, None])  # (blades, S+1, 4, 3)
    # Both broad faces split their twisted quads along parallel diagonals, so they never cross.
    vertices, faces = tubes(rings, flip=np.array([False, False, False, True]))
    colour = np.stack([pick_colour(rng, SEAWEED_PALETTE, 0.15) for _ in range(blades)])  # per blade
    shade = np.broadcast_to((0.75 + 0.45 * s)[:, :, None, None], (blades, segments + 1, 4, 1))
    rgb = (colour[:, None, None, :] * shade).reshape(-1, 3)
    return finish(vertices, faces, rgb)


def clam_valve(a: float, b: float, c: float, ribs: int, rings: int, sides: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One closed ribbed half-shell on z >= 0 with its hinge at y = -b.

    Returns vertices (2 + rings * sides, 3) metres, outward faces (F, 3), and rho (V,) in [0, 1]
    (0 at the umbo, 1 on the rim; -1 for the centre of the flat inner face).
    """
    phi = 2.0 * np.pi * np.arange(sides) / sides
    rho = (np.arange(1, rings + 1) / rings)[:, None]  # (rings, 1)
    rib = 1.0 + 0.03 * np.cos(ribs * phi)
    outline = np.stack([a * np.cos(phi) * rib, b * np.sin(phi) * rib], -1)  # (sides, 2) rim
    umbo = np.array([0.0, -0.55 * b])
    xy = umbo + rho[..., None] * (outline - umbo)  # (rings, sides, 2)
    z = c * (1.0 - rho**2) ** 0.6 * (1.0 + 0.08 * np.abs(np.cos(ribs * phi)))
    vertices, faces = valve(umbo, xy, z, c)
    rho_v = np.concatenate([[0.0], np.repeat(rho[:, 0], sides), [-1.0]])
    return vertices, faces, rho_v


def clam(rng: np.random.Generator) -> trimesh.Trimesh:
    """Clam 5-14 cm wide: two closed ribbed half-shells hinged at the back, opened 5-25 degrees (768 triangles)."""
    a = rng.uniform(0.025, 0.07)
    b = a * rng.uniform(0.75, 0.9)
    c = b * rng.uniform(0.3, 0.5)
    ribs = int(rng.integers(14, 30))
    vertices, faces, rho = clam_valve(a, b, c, ribs, rings=8, sides=24)
    shell_v, shell_f = hinged_pair(vertices, faces, -b, np.deg2rad(rng.uniform(5.0, 25.0)))
    colour = pick_colour(rng, CLAM_PALETTE, 0.15)
    bands = rng.uniform(5.0, 12.0)
    shade = 0.85 + 0.15 * np.sin(2.0 * np.pi * bands * rho)
    rgb = np.where(rho[:, None] < 0, np.clip(colour * 1.3 + 0.1, 0, 1), colour * shade[:, None])
    return finish(shell_v, shell_f, np.concatenate([rgb, rgb]))


PROCEDURAL: dict[str, Callable[[np.random.Generator], trimesh.Trimesh]] = {
    "urchin": urchin,
    "rock": rock,
    "coral": coral,
    "seaweed": seaweed,
    "clam": clam,
    "starfish": marine.starfish,
    "sea_cucumber": marine.sea_cucumber,
    "scallop": marine.scallop,
    "anemone": marine.anemone,
    "sponge": marine.sponge,
    "fish": marine.fish,
    "plastic_bottle": litter.plastic_bottle,
    "glass_bottle": litter.glass_bottle,
    "can": litter.can,
    "tyre": litter.tyre,
    "rope": litter.rope,
    "net": litter.net,
    "cinder_block": litter.cinder_block,
    "pipe": litter.pipe,
}


@functools.lru_cache(maxsize=512)
def procedural_asset(kind: str, variant: int) -> Asset:
    """Variant `variant` (>= 0) of procedural `kind`, identical in every process; cached per process."""
    if kind not in PROCEDURAL:
        raise ValueError(f"unknown procedural asset kind {kind!r}; known kinds: {', '.join(PROCEDURAL)}")
    variant = operator.index(variant)
    if variant < 0:
        raise ValueError(f"procedural asset variant must be >= 0, got {variant} for kind {kind!r}")
    rng = np.random.default_rng(np.random.SeedSequence([stable_seed(kind), variant]))
    return Asset(key=f"procedural/{kind}/{variant}", mesh=freeze(PROCEDURAL[kind](rng)),
                 sha256=None, source=f"procedural:{kind}#{variant}")
