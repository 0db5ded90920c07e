"""Motion blur and the rolling shutter: the camera moves while the shutter is open (spec `camera.exposure_s`,
`camera.readout_s`), so a frame is the average in linear light of renders at several instants of the exposure.

The motion: a survey's vehicle velocity and turn rate at the frame (seasynth.worker.scene.trajectory), or for
`random` frames a speed and turn rate drawn from `camera.velocity_m_s` and `camera.angular_rate_deg_s` in uniform
directions (the frame's motion stream). Over the exposure the camera moves at that constant velocity and turn rate
(lamps, fixed to it, move with it), centred on the frame's pose: the middle instant is exactly the frame's view.

Instants: n, odd, spaced so that the fastest-moving pixel's streak (reprojected through the middle instant's range)
moves at most about a pixel between them, at least 3 and at most MAX_INSTANTS; no motion: one (the frame as without
blur). Rolling shutter: row r (top 0) is exposed over its own window, centred (r / (h - 1) - 1/2) readout_s from the
frame's time, and averages the instants in that window (box weights).

Labels, instance ids, range and depth: each row's come from the instant nearest its window's centre. With a global
shutter that is the middle instant, the frame's own pose, so they are exactly the unblurred frame's, matching its
calib, meta pose and 3D boxes; the blurred streak of an object is centred on its box (constant velocity) rather
than boxed whole.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from seasynth.service.seeds import STREAM_MOTION, frame_rng
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.light.volume import pixel_rays
from seasynth.worker.optics.base import Plain, RenderFn, Shot
from seasynth.worker.render import RenderResult, View
from seasynth.worker.scene.trajectory import vehicle_state

MAX_INSTANTS = 33  # odd, so the middle instant is the frame's time
PIXELS_PER_INSTANT = 1.0


def rotation(axis_angle: np.ndarray) -> np.ndarray:
    """(3, 3) rotation by |axis_angle| radians about its direction (Rodrigues)."""
    angle = float(np.linalg.norm(axis_angle))
    if angle == 0.0:
        return np.eye(3)
    k = axis_angle / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx


def pose_at(world_from_cam: np.ndarray, velocity_world: np.ndarray, rate_world: np.ndarray, t_s: float) -> np.ndarray:
    """(4, 4) world_from_cam t_s seconds after the frame's time, moving at velocity_world (m/s) and turning at
    rate_world (rad/s, world axis) about the camera's centre."""
    out = np.array(world_from_cam, dtype=np.float64)
    out[:3, :3] = rotation(rate_world * t_s) @ out[:3, :3]
    out[:3, 3] += velocity_world * t_s
    return out


def frame_motion(spec: DatasetSpec, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(velocity_world m/s, angular_rate_world rad/s), each (3,) float64: the trajectory's, or for random frames
    drawn from the frame's motion stream (speed, direction, rate, axis; directions uniform on the sphere)."""
    state = vehicle_state(spec.trajectory, index)
    if state is not None:
        return state.velocity_world, state.angular_rate_world
    cam = spec.camera
    rng = frame_rng(spec.seed, index, STREAM_MOTION)
    speed = rng.uniform(*cam.velocity_m_s)
    direction = _unit(rng.normal(size=3))
    rate = math.radians(rng.uniform(*cam.angular_rate_deg_s))
    axis = _unit(rng.normal(size=3))
    return speed * direction, rate * axis


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def instants(span_s: float, n: int) -> np.ndarray:
    """(n,) float64 seconds from the frame's time: the midpoints of n equal cells of [-span/2, span/2] (n odd: the
    middle one exactly 0)."""
    return (np.arange(n) - (n - 1) / 2) * (span_s / n)


def row_weights(times: np.ndarray, span_s: float, height: int, exposure_s: float, readout_s: float) -> np.ndarray:
    """(height, n) float32: each row's weights over the instants (rows sum to 1): the overlap of each instant's
    cell with the row's exposure window; a zero-length window takes the instant whose cell holds its centre."""
    cell = span_s / len(times)
    centre = row_times(height, readout_s)
    lo = np.maximum((centre - exposure_s / 2)[:, None], times[None, :] - cell / 2)
    hi = np.minimum((centre + exposure_s / 2)[:, None], times[None, :] + cell / 2)
    w = np.clip(hi - lo, 0.0, None)
    total = w.sum(axis=1, keepdims=True)
    nearest = np.zeros_like(w)
    nearest[np.arange(height), nearest_instant(times, centre)] = 1.0
    return np.where(total > 0, w / np.where(total > 0, total, 1.0), nearest).astype(np.float32)


def row_times(height: int, readout_s: float) -> np.ndarray:
    """(height,) float64 seconds from the frame's time: the centre of each row's exposure window."""
    return (np.arange(height) / max(height - 1, 1) - 0.5) * readout_s


def nearest_instant(times: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """(len(t_s),) int: the index of the instant nearest each time (ties: the earlier)."""
    return np.argmin(np.abs(t_s[:, None] - times[None, :]), axis=1)


def streak_px(view: View, range_m: np.ndarray, start: np.ndarray, end: np.ndarray) -> float:
    """The longest image-plane path, pixels, of a static point seen by the frame's view (range_m (h, w) metres,
    +inf: a direction) between the camera poses start and end (4, 4 world_from_cam): its endpoints' distance."""
    d = pixel_rays(view.K, view.width, view.height, np.eye(4))[1]
    r = range_m.astype(np.float64)
    finite = np.isfinite(r)
    w = finite.astype(np.float64)  # homogeneous: a point, or a direction where no surface
    x, y, z = (np.where(finite, r, 1.0) * d[..., i] for i in range(3))
    world_from_view = np.linalg.inv(view.cam_from_world)
    uv = []
    for pose in (start, end):
        a = np.linalg.inv(pose) @ world_from_view  # the frame's camera -> the pose's camera
        cx, cy, cz = (a[i, 0] * x + a[i, 1] * y + a[i, 2] * z + a[i, 3] * w for i in range(3))
        with np.errstate(divide="ignore", invalid="ignore"):
            uv.append((cx / cz * view.K[0, 0], cy / cz * view.K[1, 1], cz))
    (u0, v0, z0), (u1, v1, z1) = uv
    ok = (z0 > 0) & (z1 > 0)
    if not ok.any():
        return 0.0
    return float(np.sqrt(((u0 - u1)[ok] ** 2 + (v0 - v1)[ok] ** 2).max()))


def instant_count(streak: float) -> int:
    """Instants for a streak of `streak` px: 1 without motion, else an odd count in [3, MAX_INSTANTS]."""
    if streak == 0.0:
        return 1
    return min(max(3, math.ceil(streak / PIXELS_PER_INSTANT) + 1), MAX_INSTANTS) | 1


class MotionBlur(Plain):
    name = "motion_blur"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.camera.exposure_s > 0 or spec.camera.readout_s > 0

    def prepare(self, shot: Shot) -> None:
        shot.float_image = True
        shot.needs.add("range")

    def expose(self, shot: Shot, render: RenderFn) -> RenderResult:
        cam, view = shot.spec.camera, shot.render_view
        world_from_cam = np.linalg.inv(view.cam_from_world)
        velocity, rate = frame_motion(shot.spec, shot.index)
        span = cam.exposure_s + cam.readout_s
        mid = render(view, shot.items)
        ends = [pose_at(world_from_cam, velocity, rate, t) for t in (-span / 2, span / 2)]
        streak = streak_px(view, mid.range_m, *ends)
        n = instant_count(streak)
        shot.record[self.name] = {
            "exposure_s": cam.exposure_s, "readout_s": cam.readout_s, "velocity_world_m_s": velocity.tolist(),
            "angular_rate_world_rad_s": rate.tolist(), "streak_px": streak, "instants": n}
        if n == 1:
            return mid
        times = instants(span, n)
        weights = row_weights(times, span, view.height, cam.exposure_s, cam.readout_s)
        rows = nearest_instant(times, row_times(view.height, cam.readout_s))
        image = np.zeros_like(mid.image)
        clean = None if mid.clean is None else np.zeros_like(mid.clean)
        instance = None if mid.instance is None else mid.instance.copy()
        range_m = mid.range_m.copy()
        for i, t in enumerate(times):
            pose = pose_at(world_from_cam, velocity, rate, float(t))
            res = mid if t == 0 else render(dataclasses.replace(view, cam_from_world=np.linalg.inv(pose)), shot.items)
            w = weights[:, i, None, None]
            image += w * res.image
            if clean is not None:
                clean += w * res.clean
            mine = rows == i
            if instance is not None:
                instance[mine] = res.instance[mine]
            range_m[mine] = res.range_m[mine]
        return dataclasses.replace(mid, image=image, clean=clean, instance=instance, range_m=range_m)
