"""The MCAP export's transforms (seasynth.worker.export.mcap writes them): tf2_msgs/TFMessage contents for /tf (world ->
camera, each frame) and /tf_static (camera -> each enabled sensor's frame, once a bag).

A transform parent -> child is the (4, 4) pose parent_from_child: its translation is the child's origin in the
parent's axes, its rotation (x, y, z, w, w >= 0) turns child axes into parent axes. The camera frame is the vehicle's
body frame (KITTI camera axes: x right, y down, z forward), and a sensor's frame has the same axes turned by its
spec pose: camera_from_sensor = worker.sensors.vehicle_from_sensor(sensors.{name}.pose), the matrix meta/ records
each frame composed with the camera's pose (pose_world_from_sonar, pose_world_from_sss, pose_world_from_dvl) and the
pressure and IMU readings are computed with.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from seasynth.service.spec.sensors import Sensors
from seasynth.worker.sensors import vehicle_from_sensor

CAMERA_FRAME = "camera"  # optical: x right, y down, z forward (KITTI's camera axes)
WORLD_FRAME = "world"


def rotation_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) unit quaternion of a rotation matrix (Shepperd's method), w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    k = int(np.argmax([trace, r[0, 0], r[1, 1], r[2, 2]]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q) / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(v) + 0.0 for v in q)  # type: ignore[return-value]


def transform_stamped(header: dict, child: str, parent_from_child: np.ndarray) -> dict:
    """geometry_msgs/TransformStamped of a (4, 4) float64 pose; header names the parent frame."""
    qx, qy, qz, qw = rotation_quaternion(parent_from_child[:3, :3])
    tx, ty, tz = (float(v) for v in parent_from_child[:3, 3])
    return {"header": header, "child_frame_id": child,
            "transform": {"translation": {"x": tx, "y": ty, "z": tz},
                          "rotation": {"x": qx, "y": qy, "z": qz, "w": qw}}}


def camera_tf(header: Callable[[str], dict], world_from_camera: np.ndarray) -> dict:
    """/tf of one frame: world -> camera."""
    return {"transforms": [transform_stamped(header(WORLD_FRAME), CAMERA_FRAME, world_from_camera)]}


def sensor_tf_static(header: Callable[[str], dict], sensors: Sensors) -> dict | None:
    """/tf_static: camera -> each enabled sensor, whose frame_id is its section's name under sensors: (in
    Sensors.enabled_poses' order); None with every sensor off."""
    transforms = [transform_stamped(header(CAMERA_FRAME), name, vehicle_from_sensor(pose))
                  for name, pose in sensors.enabled_poses().items()]
    return {"transforms": transforms} if transforms else None
