"""Vehicle trajectories: the camera's (= vehicle's) pose, velocity and acceleration at frame i, a pure function of
(trajectory spec, i), so any shard computes any frame's pose alone.

lawnmower: frame i is at time t = i / rate_hz and distance s = speed t along a survey of `legs` parallel legs of
leg_length_m along world +x (even legs) or -x (odd legs), leg k at y = start_y + k leg_spacing_m, at altitude_m +
heave_m sin(2 pi t / heave_period_s) above world z = 0. Turns are instantaneous (velocity jumps between legs); after
the last leg the pattern starts again at start_m (a jump). The camera looks along the leg, pitch_deg below the
horizon, with its x axis horizontal. Attitude is constant along a leg, so the angular rate is 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from seasynth.service.spec.sensors import Trajectory
from seasynth.worker.scene.poses import look_at_pose

GRAVITY = np.array([0.0, 0.0, -9.80665])  # m/s^2, world (z up)


@dataclass(frozen=True)
class VehicleState:
    t_s: float  # seconds since frame 0
    world_from_vehicle: np.ndarray  # (4, 4) float64, KITTI camera axes
    velocity_world: np.ndarray  # (3,) float64, m/s
    acceleration_world: np.ndarray  # (3,) float64, m/s^2
    angular_rate_world: np.ndarray  # (3,) float64, rad/s
    leg: int


def lawnmower_state(tr: Trajectory, index: int) -> VehicleState:
    t = index / tr.rate_hz
    s = tr.speed_m_s * t
    k = int(s // tr.leg_length_m)
    u = s - k * tr.leg_length_m
    leg = k % tr.legs
    direction = 1.0 if leg % 2 == 0 else -1.0
    w = 2 * math.pi / tr.heave_period_s
    x = tr.start_m[0] + (u if direction > 0 else tr.leg_length_m - u)
    y = tr.start_m[1] + leg * tr.leg_spacing_m
    z = tr.altitude_m + tr.heave_m * math.sin(w * t)
    eye = np.array([x, y, z])
    p = math.radians(tr.pitch_deg)
    forward = np.array([direction * math.cos(p), 0.0, -math.sin(p)])
    return VehicleState(
        t_s=t,
        world_from_vehicle=look_at_pose(eye, eye + forward),
        velocity_world=np.array([direction * tr.speed_m_s, 0.0, tr.heave_m * w * math.cos(w * t)]),
        acceleration_world=np.array([0.0, 0.0, -tr.heave_m * w * w * math.sin(w * t)]),
        angular_rate_world=np.zeros(3),
        leg=leg,
    )


def vehicle_state(tr: Trajectory, index: int) -> VehicleState | None:
    """The trajectory's state at frame `index`, or None for `random` (independent poses: no velocity)."""
    if tr.kind == "random":
        return None
    if tr.kind == "lawnmower":
        return lawnmower_state(tr, index)
    raise ValueError(f"trajectory.kind: unknown {tr.kind!r}")
