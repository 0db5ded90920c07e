"""Deterministic procedural meshes: the sea urchin and the distractors (rock, coral, seaweed, clam)."""

from __future__ import annotations

import functools
import operator
import zlib
from collections.abc import Callable

import numpy as np
import trimesh

from seasynth.worker.scene.assets import Asset, freeze


def stable_seed(name: str) -> int:
    """A process-independent 32-bit integer for `name` (CRC-32 of its UTF-8 bytes; never `hash()`)."""
    return zlib.crc32(name.encode("utf-8"))


# ---------------------------------------------------------------------------------------------
# Geometry helpers (free functions on arrays)
# ---------------------------------------------------------------------------------------------


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of `v: (n, 3) float64` scaled to unit length."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def perpendicular_frames(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit `u, v: (n, 3) float64` with (u, v, d) a right-handed orthonormal frame; `d: (n, 3)` unit."""
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    u = unit(np.cross(helper, d))
    return u, np.cross(d, u)


def smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at `lo` to 1 at `hi`; same shape as `x`."""
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def ring_points(centre: np.ndarray, axis: np.ndarray, radius: np.ndarray, sides: int) -> np.ndarray:
    """Polygon corners counter-clockwise about `axis`: (n, sides, 3) metres.

    centre, axis: (n, 3) (axis unit); radius: (n,) metres.
    """
    u, v = perpendicular_frames(axis)
    theta = 2.0 * np.pi * np.arange(sides) / sides
    offset = np.cos(theta)[None, :, None] * u[:, None] + np.sin(theta)[None, :, None] * v[:, None]
    return centre[:, None] + radius[:, None, None] * offset


def tube_faces(sections: int, sides: int, flip: np.ndarray | None = None) -> np.ndarray:
    """Outward faces (F, 3) int64 of one closed tube of `sections` rings of `sides` corners.

    Vertex `s * sides + k` is corner k of ring s; rings run along the tube axis and each ring is
    counter-clockwise about that axis. Both ends are capped with triangle fans. Side quads from
    corner k to k + 1 are split along the diagonal (k, s)-(k+1, s+1), or (k+1, s)-(k, s+1) where
    `flip: (sides,) bool` is set.
    """
    k = np.arange(sides)
    k1 = (k + 1) % sides
    s = np.arange(sections - 1)[:, None]
    a, b = s * sides + k, s * sides + k1
    c, e = a - k + k1 + sides, a + sides
    f = np.zeros(sides, bool) if flip is None else np.asarray(flip, bool)
    first = np.where(f[:, None], np.stack([a, b, e], -1), np.stack([a, b, c], -1))
    second = np.where(f[:, None], np.stack([b, c, e], -1), np.stack([a, c, e], -1))
    side = np.stack([first, second], axis=1).reshape(-1, 3)
    fan = np.arange(1, sides - 1)
    zero = np.zeros_like(fan)
    bottom = np.stack([zero, fan + 1, fan], -1)
    top = (sections - 1) * sides + np.stack([zero, fan, fan + 1], -1)
    return np.concatenate([side, bottom, top])


def tubes(rings: np.ndarray, flip: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closed tubes from `rings: (m, sections, sides, 3)` metres -> vertices (V, 3), faces (F, 3) int64."""
    m, sections, sides, _ = rings.shape
    template = tube_faces(sections, sides, flip)
    faces = template[None] + (np.arange(m) * sections * sides)[:, None, None]
    return rings.reshape(-1, 3), faces.reshape(-1, 3)


def cones(base: np.ndarray, axis: np.ndarray, length: np.ndarray, radius: np.ndarray, sides: int
          ) -> tuple[np.ndarray, np.ndarray]:
    """Closed pointed cones -> vertices (n * (sides + 1), 3) metres, outward faces (n * (2 sides - 2), 3).

    base, axis: (n, 3) metres / unit; length, radius: (n,) metres. Per cone: `sides` base corners, then the tip.
    """
    n = len(base)
    ring = ring_points(base, axis, radius, sides)
    tip = base + length[:, None] * axis
    vertices = np.concatenate([ring, tip[:, None]], axis=1).reshape(-1, 3)
    k = np.arange(sides)
    fan = np.arange(1, sides - 1)
    template = np.concatenate([
        np.stack([k, (k + 1) % sides, np.full(sides, sides)], -1),
        np.stack([np.zeros_like(fan), fan + 1, fan], -1),
    ])
    faces = template[None] + (np.arange(n) * (sides + 1))[:, None, None]
    return vertices, faces.reshape(-1, 3)


def wave_field(rng: np.random.Generator, p: np.ndarray, waves: int, frequency: float) -> np.ndarray:
    """Smooth random field at points `p: (n, 3)`: sum of random plane waves, unit RMS; (n,) float64."""
    k = rng.normal(size=(waves, 3)) * frequency
    phase = rng.uniform(0.0, 2.0 * np.pi, waves)
    amplitude = 1.0 / (1.0 + np.linalg.norm(k, axis=1))
    field = np.sin(p @ k.T + phase) @ amplitude
    return field / np.sqrt(np.mean(field**2))


def srgb_u8(rgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded colours `rgb: (n, 3)` in [0, 1] -> opaque RGBA (n, 4) uint8."""
    out = np.full((len(rgb), 4), 255, dtype=np.uint8)
    out[:, :3] = np.round(np.clip(rgb, 0.0, 1.0) * 255.0)
    return out


def finish(vertices: np.ndarray, faces: np.ndarray, rgb: np.ndarray) -> trimesh.Trimesh:
    """Mesh resting on z = 0 with its x, y bounding box centred on 0; `rgb: (n, 3)` sRGB in [0, 1]."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    shift = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    return trimesh.Trimesh(vertices=vertices - shift, faces=faces, vertex_colors=srgb_u8(rgb),
                           process=False)


def pick_colour(rng: np.random.Generator, palette: np.ndarray, spread: float) -> np.ndarray:
    """One sRGB colour (3,) from `palette: (k, 3)` with multiplicative jitter of about `spread`."""
    base = palette[rng.integers(len(palette))]
    return np.clip(base * rng.uniform(1.0 - spread, 1.0 + spread) + rng.normal(0.0, spread / 8, 3), 0, 1)


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
    vertices = np.concatenate([[[*umbo, c]], np.concatenate([xy, z[..., None]], -1).reshape(-1, 3),
                               [[*umbo, 0.0]]])
    k = np.arange(sides)
    k1 = (k + 1) % sides
    i = np.arange(rings - 1)[:, None]
    a_, b_ = 1 + i * sides + k, 1 + i * sides + k1
    quads = np.stack([np.stack([a_, a_ + sides, b_ + sides], -1),
                      np.stack([a_, b_ + sides, b_], -1)], axis=1).reshape(-1, 3)
    rim = 1 + (rings - 1) * sides
    centre = len(vertices) - 1
    faces = np.concatenate([np.stack([np.zeros(sides, int), 1 + k, 1 + k1], -1), quads,
                            np.stack([np.full(sides, centre), rim + k1, rim + k], -1)])
    rho_v = np.concatenate([[0.0], np.repeat(rho[:, 0], sides), [-1.0]])
    return vertices, faces, rho_v


def clam(rng: np.random.Generator) -> trimesh.Trimesh:
    """Clam 5-14 cm wide: two closed ribbed half-shells hinged at the back, opened 5-25 degrees (768 triangles)."""
    a = rng.uniform(0.025, 0.07)
    b = a * rng.uniform(0.75, 0.9)
    c = b * rng.uniform(0.3, 0.5)
    ribs = int(rng.integers(14, 30))
    vertices, faces, rho = clam_valve(a, b, c, ribs, rings=8, sides=24)
    lower = vertices * [1.0, 1.0, -1.0]
    hinge_y = -b
    opening = np.deg2rad(rng.uniform(5.0, 25.0))
    cos, sin = np.cos(opening), np.sin(opening)
    upper = np.column_stack([vertices[:, 0],
                             hinge_y + (vertices[:, 1] - hinge_y) * cos - vertices[:, 2] * sin,
                             (vertices[:, 1] - hinge_y) * sin + vertices[:, 2] * cos])
    colour = pick_colour(rng, CLAM_PALETTE, 0.15)
    bands = rng.uniform(5.0, 12.0)
    shade = 0.85 + 0.15 * np.sin(2.0 * np.pi * bands * rho)
    rgb = np.where(rho[:, None] < 0, np.clip(colour * 1.3 + 0.1, 0, 1), colour * shade[:, None])
    return finish(np.concatenate([lower, upper]),
                  np.concatenate([faces[:, ::-1], faces + len(vertices)]),  # mirror flips the winding
                  np.concatenate([rgb, rgb]))


PROCEDURAL: dict[str, Callable[[np.random.Generator], trimesh.Trimesh]] = {
    "urchin": urchin,
    "rock": rock,
    "coral": coral,
    "seaweed": seaweed,
    "clam": clam,
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
