"""Sensors besides the camera: one module per sensor (fls, nav), sharing the vehicle-to-sensor pose convention here.

The vehicle's body frame is the camera's (KITTI axes: x right, y down, z forward, metres); every sensor frame uses
the same axes, so a sensor at the vehicle's origin with pitch 0 and yaw 0 looks where the camera looks.
"""

from __future__ import annotations

import math

import numpy as np

from seasynth.service.spec.sensors import SensorPose


def vehicle_from_sensor(pose: SensorPose) -> np.ndarray:
    """(4, 4) float64: the sensor's frame in the vehicle's. Pitch tilts the forward axis down (towards +y), then
    yaw turns it to starboard (+x): R = R_y(yaw) R_x(-pitch)."""
    p, y = math.radians(pose.pitch_deg), math.radians(pose.yaw_deg)
    Rx = np.array([[1.0, 0, 0], [0, math.cos(-p), -math.sin(-p)], [0, math.sin(-p), math.cos(-p)]])
    Ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1.0, 0], [-math.sin(y), 0, math.cos(y)]])
    T = np.eye(4)
    T[:3, :3] = Ry @ Rx
    T[:3, 3] = pose.offset_m
    return T


def world_from_sensor(world_from_vehicle: np.ndarray, pose: SensorPose) -> np.ndarray:
    """(4, 4) float64 world_from_sensor for a vehicle pose (4, 4) float64."""
    return world_from_vehicle @ vehicle_from_sensor(pose)
