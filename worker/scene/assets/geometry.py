"""Geometry helpers of the procedural meshes (free functions on arrays): frames, rings, tubes, cones, surfaces of
revolution, hinged shells, and the finishing of a mesh (its rest position and vertex colours)."""

from __future__ import annotations

import numpy as np
import trimesh


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


def finish(vertices: np.ndarray, faces: np.ndarray, rgb: np.ndarray, centred: bool = False) -> trimesh.Trimesh:
    """Mesh resting on z = 0 with its x, y bounding box centred on 0; `rgb: (n, 3)` sRGB in [0, 1]. centred: its
    whole bounding box centred on 0 instead (an object in the water column)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    shift = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0 if centred else lo[2]])
    return trimesh.Trimesh(vertices=vertices - shift, faces=faces, vertex_colors=srgb_u8(rgb),
                           process=False)


def widened(vertices: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """`vertices: (n, 3)` moved away from the z axis by `factor: (n,)` (heights kept)."""
    return vertices * np.column_stack([factor, factor, np.ones(len(factor))])


def pick_colour(rng: np.random.Generator, palette: np.ndarray, spread: float) -> np.ndarray:
    """One sRGB colour (3,) from `palette: (k, 3)` with multiplicative jitter of about `spread`."""
    base = palette[rng.integers(len(palette))]
    return np.clip(base * rng.uniform(1.0 - spread, 1.0 + spread) + rng.normal(0.0, spread / 8, 3), 0, 1)


def loop_faces(sections: int, sides: int) -> np.ndarray:
    """Outward faces (F, 3) int64 of a closed ring of `sections` rings of `sides` corners (a torus: the last ring
    joins the first); vertex `s * sides + k` as in tube_faces, rings counter-clockwise about the direction of travel."""
    k = np.arange(sides)
    k1 = (k + 1) % sides
    s = np.arange(sections)[:, None]
    s1 = (s + 1) % sections
    a, b, c, e = s * sides + k, s * sides + k1, s1 * sides + k1, s1 * sides + k
    return np.stack([np.stack([a, b, c], -1), np.stack([a, c, e], -1)], axis=1).reshape(-1, 3)


def revolve(r: np.ndarray, z: np.ndarray, sides: int, closed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A solid of revolution about +z from a profile `r, z: (..., S)` metres (r > 0), traversed with the solid on its
    left in the (r, z) half-plane (up the outside, down the inside) -> vertices (V, 3), outward faces (F, 3).

    Open profiles are capped flat at both ends (fans: each end's ring is a circle); closed ones (`closed`: the last point
    joins the first) give a ring-shaped solid: a tyre, a pipe with its wall. Leading axes are separate solids.
    """
    theta = 2.0 * np.pi * np.arange(sides) / sides
    rings = np.stack([r[..., None] * np.cos(theta), r[..., None] * np.sin(theta),
                      np.broadcast_to(z[..., None], r.shape + (sides,))], -1).reshape(-1, r.shape[-1], sides, 3)
    if not closed:
        return tubes(rings)
    m, sections = rings.shape[:2]
    faces = loop_faces(sections, sides)[None] + (np.arange(m) * sections * sides)[:, None, None]
    return rings.reshape(-1, 3), faces.reshape(-1, 3)


def plates(outline: np.ndarray, origin: np.ndarray, e1: np.ndarray, e2: np.ndarray, thickness: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Thin closed plates (fins, blades) -> vertices (V, 3), outward faces (F, 3).

    outline: (k, 2) polygon counter-clockwise in (e1, e2) coordinates, star-shaped about its first corner (the caps
    are fans from it); origin, e1, e2: (n, 3) metres / unit per plate; thickness: (n,) metres, along e1 x e2.
    """
    normal = np.cross(e1, e2)
    flat = origin[:, None] + outline[None, :, :1] * e1[:, None] + outline[None, :, 1:] * e2[:, None]
    half = 0.5 * thickness[:, None, None] * normal[:, None]
    return tubes(np.stack([flat - half, flat + half], axis=1))


def valve(umbo: np.ndarray, xy: np.ndarray, z: np.ndarray, apex: float) -> tuple[np.ndarray, np.ndarray]:
    """One closed half-shell over z >= 0 -> vertices (2 + rings * sides, 3) metres, outward faces (F, 3).

    umbo: (2,) its apex's x, y; xy: (rings, sides, 2) growth rings from the umbo out to the rim, each counter-clockwise;
    z: (rings, sides) their heights; apex: the umbo's height. The flat inner face closes it at z = 0.
    """
    rings, sides = z.shape
    vertices = np.concatenate([[[*umbo, apex]], np.concatenate([xy, z[..., None]], -1).reshape(-1, 3),
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
    return vertices, faces


def hinged_pair(vertices: np.ndarray, faces: np.ndarray, hinge_y: float, opening: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """A bivalve from one valve (`valve`'s vertices (V, 3), faces): its mirror below z = 0 and itself opened by
    `opening` radians about the hinge line y = hinge_y -> vertices (2V, 3), outward faces (2F, 3)."""
    lower = vertices * [1.0, 1.0, -1.0]
    cos, sin = np.cos(opening), np.sin(opening)
    upper = np.column_stack([vertices[:, 0],
                             hinge_y + (vertices[:, 1] - hinge_y) * cos - vertices[:, 2] * sin,
                             (vertices[:, 1] - hinge_y) * sin + vertices[:, 2] * cos])
    return (np.concatenate([lower, upper]),
            np.concatenate([faces[:, ::-1], faces + len(vertices)]))  # the mirror flips the winding


def capped(rings: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed body from `rings: (S, sides, 3)` metres along its axis (each counter-clockwise about the direction
    of travel) and `ends: (2, 3)` its two tips (before the first ring, after the last) -> vertices (S * sides + 2, 3)
    and outward faces (F, 3): the side of tube_faces and a fan from each tip, so no ring needs to be convex."""
    sections, sides = rings.shape[:2]
    k = np.arange(sides)
    k1 = (k + 1) % sides
    side = tube_faces(sections, sides)[: 2 * (sections - 1) * sides]
    first, last = sections * sides, sections * sides + 1
    top = (sections - 1) * sides
    faces = np.concatenate([side, np.stack([np.full(sides, first), k1, k], -1),
                            np.stack([np.full(sides, last), top + k, top + k1], -1)])
    return np.concatenate([rings.reshape(-1, 3), ends]), faces
