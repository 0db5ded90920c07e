"""Object placement: a pose on, in or above the seabed that keeps clear of the objects placed before it.

Non-overlap rule: each object lies in the vertical cylinder over its footprint disc (about its anchor, the pose's
translation) between the heights of its z span. An object standing on or in the seabed spans from -inf (nothing
fits under it) to its top. Two objects whose discs overlap must have disjoint spans; two on the seabed therefore
never share ground, as before objects could float.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from seasynth.service.spec.scene import Box
from seasynth.service.spec.targets import Buried, InWater, Seabed
from seasynth.worker.scene.assets import Asset
from seasynth.worker.scene.assets.terrain import Terrain
from seasynth.worker.scene.poses import rotation_between

PLACEMENT_TRIES = 24  # per object, before it is left out
UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Pose:
    """Where one object goes: its pose, footprint and z span (see the module's rule) and what its placement drew."""

    world_from_obj: np.ndarray  # (4, 4) float64, metres, world z up: rotation times scale, then translation
    footprint_m: float  # metres: radius of the disc about the anchor holding the object's horizontal projection
    z_span: tuple[float, float]  # world metres: lowest, highest point; lowest -inf on or in the seabed
    drawn: dict  # the placement's draws for meta: {"sunk_fraction": f} or {"height_m": h}, {} on the seabed


@dataclass(frozen=True)
class Neighbours:
    """The objects placed so far, as the non-overlap rule sees them."""

    anchors: np.ndarray  # (n, 2) float64 world xy, metres
    radii: np.ndarray  # (n,) float64 metres
    spans: np.ndarray  # (n, 2) float64 world z, metres

    def clear(self, xy: np.ndarray, radius: float, span: tuple[float, float]) -> bool:
        """Whether an object at xy (2,) with this footprint and span overlaps none of them."""
        if not self.anchors.size:
            return True
        near = np.linalg.norm(self.anchors - xy, axis=1) < self.radii + radius
        return not np.any(near & (self.spans[:, 0] < span[1]) & (span[0] < self.spans[:, 1]))


def neighbours(placed) -> Neighbours:
    """Neighbours of placed objects (anything with world_from_obj, footprint_m and z_span)."""
    return Neighbours(anchors=np.array([p.world_from_obj[:2, 3] for p in placed]).reshape(-1, 2),
                      radii=np.array([p.footprint_m for p in placed], dtype=np.float64),
                      spans=np.array([p.z_span for p in placed], dtype=np.float64).reshape(-1, 2))


def in_box(points: np.ndarray, box: Box) -> np.ndarray:
    """(n,) bool: which of (n, 3) points lie in the box (bounds included)."""
    return np.all((points >= np.asarray(box.min)) & (points <= np.asarray(box.max)), axis=1)


_CANDIDATES: dict[tuple[str, Box], np.ndarray] = {}


def candidates(terrain: Terrain, box: Box) -> np.ndarray:
    """Indices of terrain vertices inside a workspace box (cached per process: terrains and boxes repeat)."""
    key = (terrain.key, box)
    got = _CANDIDATES.get(key)
    if got is None:
        if len(_CANDIDATES) >= 256:
            _CANDIDATES.clear()
        got = _CANDIDATES[key] = np.flatnonzero(in_box(np.asarray(terrain.mesh.vertices), box))
    return got


_EXTREMES: dict[str, np.ndarray] = {}


def extreme_points(asset: Asset) -> np.ndarray:
    """(k, 3) float64: the asset's convex hull vertices, or all its vertices where it has no 3D hull (flat).

    A footprint's radius and an object's z span are extremes of linear images of the vertices, reached at hull
    vertices: measuring only those is exact, and cheap for large user meshes. Cached per process.
    """
    got = _EXTREMES.get(asset.key)
    if got is None:
        from scipy.spatial import ConvexHull, QhullError

        verts = np.asarray(asset.mesh.vertices, dtype=np.float64)
        try:
            got = verts[ConvexHull(verts).vertices]
        except (QhullError, ValueError):  # coplanar, collinear or too few points: measure them all
            got = verts
        if len(_EXTREMES) >= 1024:
            _EXTREMES.clear()
        _EXTREMES[asset.key] = got
    return got


def footprint_radius(vertices: np.ndarray, linear: np.ndarray) -> float:
    """Radius (metres) of the disc about the anchor that holds the object's horizontal projection as placed.

    vertices: (n, 3) float64, object metres; linear: (3, 3) world_from_obj's rotation times scale. Two objects
    whose discs do not overlap cannot interpenetrate: each lies in the vertical cylinder over its disc.
    """
    xy = vertices @ linear[:2].T
    return float(np.sqrt(np.einsum("ij,ij->i", xy, xy).max()))


_EDGES: dict[str, float] = {}


def _longest_edge_xy(terrain: Terrain) -> float:
    """Metres: the terrain's longest triangle edge projected on the horizontal plane (cached per terrain)."""
    got = _EDGES.get(terrain.key)
    if got is None:
        v = np.asarray(terrain.mesh.vertices)[:, :2]
        e = np.asarray(terrain.mesh.edges_unique)
        got = float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).max()) if len(e) else 0.0
        if len(_EDGES) >= 256:
            _EDGES.clear()
        _EDGES[terrain.key] = got
    return got


def seabed_top(terrain: Terrain, xy: np.ndarray, radius: float) -> float:
    """Metres: an upper bound of the seabed's height over the disc of `radius` about xy (2,), tight to the mesh.

    Every point of the disc lies in a triangle whose corners are within radius + the longest edge of xy, and a
    triangle's height is at most its highest corner's."""
    v = np.asarray(terrain.mesh.vertices)
    reach = radius + _longest_edge_xy(terrain)
    d2 = np.einsum("ij,ij->i", v[:, :2] - xy, v[:, :2] - xy)
    near = v[d2 <= reach * reach, 2]
    return float(near.max()) if near.size else float(terrain.height_at(xy[None])[0])


def rotation_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) Rz(yaw) Ry(pitch) Rx(roll), radians: heading about world z, then pitch, then roll about the body."""
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch), math.cos(roll),
                              math.sin(roll))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def _pose(linear: np.ndarray, position: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = linear
    T[:3, 3] = position
    return T


def place(rng: np.random.Generator, terrain: Terrain, box: Box, asset: Asset, scale: float,
          placement: Seabed | Buried | InWater, others: Neighbours) -> Pose | None:
    """A pose for `asset` in `box` as `placement` says that overlaps none of `others`, or None after
    PLACEMENT_TRIES draws. Seabed draws exactly what placement drew before placements had kinds."""
    cands = candidates(terrain, box)
    if cands.size == 0:
        return None
    if isinstance(placement, InWater):
        return _in_water(rng, terrain, cands, asset, scale, placement, others)
    sunk = float(rng.uniform(*placement.sunk_fraction)) if isinstance(placement, Buried) else None
    verts = np.asarray(terrain.mesh.vertices)
    normals = np.asarray(terrain.mesh.vertex_normals)
    obj_verts = extreme_points(asset)
    height = float(np.ptp(obj_verts[:, 2])) * scale
    for _ in range(PLACEMENT_TRIES):
        idx = cands[rng.integers(cands.size)]
        yaw = rng.uniform(0.0, 2 * math.pi)
        pos = verts[idx]
        n = normals[idx] / max(np.linalg.norm(normals[idx]), 1e-12)
        c, s = math.cos(yaw), math.sin(yaw)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        linear = rotation_between(UP, n) @ Rz * scale
        if sunk is not None:  # down along the normal by the drawn fraction of its height
            pos = pos - n * (sunk * height)
        # Measured as placed: on a slope a tall object leans out past its upright footprint (2.5x seen).
        radius = footprint_radius(obj_verts, linear)
        top = float(pos[2] + (obj_verts @ linear[2]).max())
        if not others.clear(pos[:2], radius, (-math.inf, top)):
            continue
        return Pose(_pose(linear, pos), radius, (-math.inf, top), {} if sunk is None else {"sunk_fraction": sunk})
    return None


def _in_water(rng: np.random.Generator, terrain: Terrain, cands: np.ndarray, asset: Asset, scale: float,
              placement: InWater, others: Neighbours) -> Pose | None:
    verts = np.asarray(terrain.mesh.vertices)
    obj_verts = extreme_points(asset)
    for _ in range(PLACEMENT_TRIES):
        xy = verts[cands[rng.integers(cands.size)], :2]
        yaw, pitch, roll = np.radians([rng.uniform(*placement.yaw_deg), rng.uniform(*placement.pitch_deg),
                                       rng.uniform(*placement.roll_deg)])
        height = float(rng.uniform(*placement.height_m))
        pose = water_pose(terrain, obj_verts, scale, xy, rotation_zyx(yaw, pitch, roll), height)
        if others.clear(xy, pose.footprint_m, pose.z_span):
            return pose
    return None


def water_pose(terrain: Terrain, obj_verts: np.ndarray, scale: float, xy: np.ndarray, rotation: np.ndarray,
               height: float) -> Pose:
    """The pose of an object with anchor xy (2,) and rotation (3, 3) whose lowest point is `height` metres above
    the highest seabed under its footprint."""
    linear = rotation * scale
    radius = footprint_radius(obj_verts, linear)
    z = obj_verts @ linear[2]
    bottom = seabed_top(terrain, xy, radius) + height
    anchor_z = bottom - float(z.min())
    span = (bottom, anchor_z + float(z.max()))
    return Pose(_pose(linear, np.array([xy[0], xy[1], anchor_z])), radius, span, {"height_m": height})


def place_school(rng: np.random.Generator, terrain: Terrain, box: Box, members: list[tuple[Asset, float]],
                 placement: InWater, others: Neighbours) -> list[Pose | None]:
    """Poses of a school's members ((asset, scale) each), None for each left out: the first is placed as one
    object in the water; the others line up abreast of it, each spacing_m (drawn per school) beyond its
    neighbour's footprint, at the school's height above the seabed, heading the school's way within
    heading_jitter_deg, and each clear of every object placed before it. A school of none (school.size's min may
    be 0) places nothing and draws nothing."""
    if not members:
        return []
    school = placement.school
    spacing = float(rng.uniform(*school.spacing_m))
    cands = candidates(terrain, box)
    first = _in_water(rng, terrain, cands, members[0][0], members[0][1], placement, others) if cands.size else None
    poses: list[Pose | None] = [first]
    if first is None:
        return poses + [None] * (len(members) - 1)
    heading = math.atan2(first.world_from_obj[1, 0], first.world_from_obj[0, 0])
    side = np.array([-math.sin(heading), math.cos(heading)])
    xy, reach = first.world_from_obj[:2, 3], first.footprint_m
    placed = [first]
    for asset, scale in members[1:]:
        yaw = heading + math.radians(rng.uniform(-school.heading_jitter_deg, school.heading_jitter_deg))
        pitch, roll = np.radians([rng.uniform(*placement.pitch_deg), rng.uniform(*placement.roll_deg)])
        obj_verts = extreme_points(asset)
        radius = footprint_radius(obj_verts, rotation_zyx(yaw, pitch, roll) * scale)
        xy = xy + side * (reach + spacing + radius)
        reach = radius
        pose = water_pose(terrain, obj_verts, scale, xy, rotation_zyx(yaw, pitch, roll), first.drawn["height_m"])
        ok = others.clear(xy, pose.footprint_m, pose.z_span) and neighbours(placed).clear(xy, pose.footprint_m,
                                                                                          pose.z_span)
        poses.append(pose if ok else None)
        if ok:
            placed.append(pose)
    return poses
