"""Shadow-map geometry: the matrices that take camera-frame points to a light's shadow-map coordinates.

A map's coordinates are (s, t) in [0, 1] across the texture and r in [0, 1] the depth the map compares against;
the renderer draws the map with `light_clip_from_world` and shades with `map_from_cam`.
"""

from __future__ import annotations

import math

import numpy as np

SUN_MAP_SIZE = 2048  # texels a side
LAMP_MAP_SIZE = 1024

# NDC [-1, 1] -> texture [0, 1] in x, y and z.
_BIAS = np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 0.5, 0.5], [0, 0, 0, 1.0]])


def frame_looking(direction: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4, 4) light_from_world: a right-handed frame at origin whose -z looks along `direction` (GL's habit)."""
    f = np.asarray(direction, dtype=np.float64)
    f = f / np.linalg.norm(f)
    helper = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(f, helper)
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    R = np.stack([x, y, -f])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.asarray(origin, dtype=np.float64)
    return T


def orthographic(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(4, 4) GL orthographic projection of the light-frame box [lo, hi] (z negative in front)."""
    l, b, n = lo[0], lo[1], -hi[2]
    r, t, f = hi[0], hi[1], -lo[2]
    return np.array([
        [2 / (r - l), 0, 0, -(r + l) / (r - l)],
        [0, 2 / (t - b), 0, -(t + b) / (t - b)],
        [0, 0, -2 / (f - n), -(f + n) / (f - n)],
        [0, 0, 0, 1.0],
    ])


def perspective(half_angle: float, near: float, far: float) -> np.ndarray:
    """(4, 4) GL perspective projection with a square field of view of +-half_angle."""
    f = 1.0 / math.tan(half_angle)
    return np.array([
        [f, 0, 0, 0],
        [0, f, 0, 0],
        [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
        [0, 0, -1.0, 0],
    ])


def sun_clip_from_world(sun_dir_world: np.ndarray, spheres: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """Orthographic clip_from_world of a directional light (towards the sun: sun_dir_world) fitted to bounding
    spheres (world centre, radius) of everything that casts or receives shadows; with none, a unit sphere at the
    origin (the map then holds nothing, and nothing is shadowed)."""
    spheres = spheres or [(np.zeros(3), 1.0)]
    centres = np.array([c for c, _ in spheres], dtype=np.float64).reshape(-1, 3)
    radii = np.array([r for _, r in spheres], dtype=np.float64)
    mid = (centres.min(axis=0) + centres.max(axis=0)) / 2 if len(centres) else np.zeros(3)
    view = frame_looking(-np.asarray(sun_dir_world), mid)
    pts = centres @ view[:3, :3].T + view[:3, 3]
    lo = (pts - radii[:, None]).min(axis=0) - 1e-3
    hi = (pts + radii[:, None]).max(axis=0) + 1e-3
    return orthographic(lo, hi) @ view


def sun_texel_m(clip_from_world: np.ndarray, size: int) -> float:
    """Metres per texel of a sun map of `size` texels a side drawn with this orthographic clip (the larger side)."""
    extent = 2.0 / np.linalg.norm(clip_from_world[:2, :3], axis=1)
    return float(extent.max()) / size


def soft_map_size(clip_from_world: np.ndarray, radius_m: float) -> int:
    """Texels a side of the sun's coarse map, whose filtered tap blurs over about one texel: the power of two whose
    texel is at most radius_m (at least 16, at most SUN_MAP_SIZE; powers of two keep few targets alive)."""
    texels = sun_texel_m(clip_from_world, 1) / radius_m
    return int(min(max(16, 2 ** math.ceil(math.log2(max(texels, 1.0)))), SUN_MAP_SIZE))


# A lamp's map reaches this far past its cutoff: its forward-scattered light spreads past the cutoff
# (lamps.light_factor), and surfaces beyond the map get none of it (the resolve shader's lamp_tap). Measured on the
# fidelity bench's turbid-lamps scene: 15 degrees keeps the glow's effect on surfaces (block PSNR 34.5 dB against
# 31.5 with 2 degrees; 30 and 45 gain < 0.1 dB) and costs clear water 0.07 dB of shadow sharpness.
LAMP_MAP_MARGIN_RAD = math.radians(15.0)


def _lamp_half_angle(cutoff_rad: float) -> float:
    return min(cutoff_rad + LAMP_MAP_MARGIN_RAD, math.radians(80.0))


def lamp_clip_from_cam(position_cam: np.ndarray, direction_cam: np.ndarray, cutoff_rad: float, far: float):
    """Perspective clip_from_cam of a spot light covering its cone."""
    return perspective(_lamp_half_angle(cutoff_rad), 0.01, far) @ frame_looking(direction_cam, position_cam)


def lamp_texel(cutoff_rad: float) -> float:
    """A lamp map texel's width in metres per metre from the lamp (on its axis)."""
    return 2.0 * math.tan(_lamp_half_angle(cutoff_rad)) / LAMP_MAP_SIZE


def texture_from_clip(clip_from_x: np.ndarray) -> np.ndarray:
    """(4, 4): points of frame x to shadow-map texture coordinates (homogeneous; divide by w for a lamp)."""
    return _BIAS @ clip_from_x
