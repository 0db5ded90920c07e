"""ROS 2 bag export in MCAP: one OUT/{split}.mcap per split, for replay in Foxglove, rviz2 or `ros2 bag play`.

Written with the PyPI packages mcap and mcap-ros2-support (no ROS install): profile "ros2", CDR messages,
schemas as ros2msg text (the type's .msg, then each type it uses after a line of 80 "=" and "MSG: pkg/Type",
as rosbag2 writes them), zstd chunks. Frames come in ascending index, each stamped (from 0, the epoch) in every
message's header.stamp and as the record's log and publish time: a `lawnmower` survey's frame i at its time on the
survey, round(i * 1e9 / trajectory.rate_hz) ns (seasynth.worker.scene.trajectory flies frame i at i / rate_hz s); independent
`random` frames at a nominal i / FRAME_RATE_HZ s, exactly (stamp_ns). Topics:

  /camera/image/compressed  sensor_msgs/msg/CompressedImage  format "png" (or "jpeg" with outputs.image_format
                            jpeg): the image_2 file's bytes as they are
  /camera/camera_info       sensor_msgs/msg/CameraInfo       K and P (= [K | 0]) from calib's P2, R = I,
                                                             "plumb_bob" with d = the spec's camera.distortion
                                                             [k1, k2, p1, p2, k3] (empty without one). A housing's
                                                             port is beyond CameraInfo: the metadata record's
                                                             "camera_model" holds it (as meta/ does)
  /detections               vision_msgs/msg/Detection2DArray one Detection2D per label line (then distractors):
                                                             bbox centre and size in pixel-edge coordinates of
                                                             the KITTI box, one hypothesis (class name, 1.0);
                                                             id "k", its 0-based place in the array: a target's
                                                             label_2 line, then the distractors (--distractors)
                                                             in ascending instance id, so a target's id is the
                                                             same with or without --distractors; DontCare
                                                             lines (spec labels filters) are left out
  /tf_static                tf2_msgs/msg/TFMessage           camera -> each enabled sensor's frame (fls, sss,
                                                             dvl, pressure, imu): its sensors.*.pose
                                                             (seasynth.worker.export.mcap_tf); once a bag, before its
                                                             first frame's messages, stamped with it
  /tf                       tf2_msgs/msg/TFMessage           world -> camera, meta's pose_world_from_camera
                                                             (only when the dataset has meta/)
  /camera/depth             sensor_msgs/msg/Image            "32FC1" z-depth in metres, NaN where none (only
                                                             when the dataset has depth/)
  /fls/..., /sss/..., /dvl/twist, /pressure, /imu: the sonar and navigation sensors the spec switches on
  (seasynth.worker.export.mcap_sensors lists them)

Each channel carries the ROS 2 profile's offered_qos_profiles (offered_qos): reliable, and /tf_static transient
local, so `ros2 bag play` latches it as a static broadcaster does. Header frame_id is "camera" (tf's is "world"):
KITTI's camera axes (x right, y down, z forward) are ROS's optical frame convention, so "camera" is an optical
frame. A metadata record "seasynth" gives the frame rate (the survey's
rate_hz, or FRAME_RATE_HZ), the stamp rule, the split, the categories (a JSON list of class names, the target's
then "distractor" with --distractors) and the dataset's seed, spec digest and code version. The same
dataset exports to the same bytes (with the same mcap and mcap-ros2-support versions, which the file's header names).
"""

from __future__ import annotations

import json
import os
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.spec.outputs import SPLITS
from seasynth.service.spec.sensors import Trajectory
from seasynth.worker.export.base import ExportInfo
from seasynth.worker.export.dataset import Frame, camera_pose, camera_projection, depth_metres
from seasynth.worker.export.files import make_dirs, tmp_name
from seasynth.worker.export.mcap_sensors import SENSOR_DEFS, SENSOR_TOPICS, sensor_messages
from seasynth.worker.export.mcap_tf import CAMERA_FRAME, camera_tf, sensor_tf_static

FRAME_RATE_HZ = 10  # random frame i is stamped i / 10 s: frames are independent scenes, so the rate is nominal
NS_PER_S = 1_000_000_000
INSTALL_HINT = "pip install -e '.[export]'"

SEPARATOR = "=" * 80

_DEFS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                          "uint8 is_bigendian\nuint32 step\nuint8[] data\n"),
    "sensor_msgs/RegionOfInterest": ("uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
                                     "bool do_rectify\n"),
    "sensor_msgs/CameraInfo": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
                               "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
                               "uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n"),
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/TransformStamped": ("std_msgs/Header header\nstring child_frame_id\n"
                                       "geometry_msgs/Transform transform\n"),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "vision_msgs/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/ObjectHypothesisWithPose": ("vision_msgs/ObjectHypothesis hypothesis\n"
                                             "geometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/Detection2D": ("std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                "vision_msgs/BoundingBox2D bbox\nstring id\n"),
    "vision_msgs/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
    **SENSOR_DEFS,
}


def _uses(name: str) -> list[str]:
    """The message types `name`'s definition names, in order of first use, depth first (rosbag2's order)."""
    out: list[str] = []

    def visit(n: str) -> None:
        for line in _DEFS[n].splitlines():
            t = line.split()[0].split("[")[0]
            if "/" in t and t not in out:
                out.append(t)
                visit(t)

    visit(name)
    return out


def msgdef(datatype: str) -> str:
    """The ros2msg schema text of "pkg/msg/Type": its definition, then every type it uses."""
    pkg, _, name = datatype.split("/")
    short = f"{pkg}/{name}"
    return _DEFS[short] + "".join(f"{SEPARATOR}\nMSG: {t}\n{_DEFS[t]}" for t in _uses(short))


# topic -> message type
IMAGE_TOPIC, INFO_TOPIC, DETECTIONS_TOPIC, TF_TOPIC, DEPTH_TOPIC, TF_STATIC_TOPIC = (
    "/camera/image/compressed", "/camera/camera_info", "/detections", "/tf", "/camera/depth", "/tf_static")
TOPICS = {
    IMAGE_TOPIC: "sensor_msgs/msg/CompressedImage",
    INFO_TOPIC: "sensor_msgs/msg/CameraInfo",
    DETECTIONS_TOPIC: "vision_msgs/msg/Detection2DArray",
    TF_TOPIC: "tf2_msgs/msg/TFMessage",
    TF_STATIC_TOPIC: "tf2_msgs/msg/TFMessage",
    DEPTH_TOPIC: "sensor_msgs/msg/Image",
    **SENSOR_TOPICS,
}


# The ROS 2 profile's channel metadata: offered_qos_profiles, a YAML list of the QoS the topic was offered with, as
# rosbag2 writes it (rmw enums as integers; infinite durations as rmw's). `ros2 bag play` offers each topic with it:
# /tf_static must be transient-local (latched), or a listener that subscribes after its one message never gets it.
_QOS = ("- history: 3\n  depth: 0\n  reliability: 1\n  durability: {durability}\n"
        "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: 1\n"
        "  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  avoid_ros_namespace_conventions: false")
TRANSIENT_LOCAL, VOLATILE = 1, 2  # rmw_qos_durability_policy_e


def offered_qos(topic: str) -> dict[str, str]:
    """A channel's metadata: reliable, latched (transient local) for /tf_static, volatile for every other topic."""
    return {"offered_qos_profiles": _QOS.format(durability=TRANSIENT_LOCAL if topic == TF_STATIC_TOPIC else VOLATILE)}


def stamp_ns(index: int, trajectory: Trajectory) -> int:
    """Frame `index`'s time in ns: round(index * 1e9 / rate_hz) on a survey (the time seasynth.worker.scene.trajectory flies it at),
    index / FRAME_RATE_HZ s exactly for independent `random` frames."""
    if trajectory.kind == "random":
        return index * NS_PER_S // FRAME_RATE_HZ
    return round(index * NS_PER_S / trajectory.rate_hz)


def clock_metadata(trajectory: Trajectory) -> dict[str, str]:
    """The "seasynth" metadata's frame_rate_hz and stamp_rule, as stamp_ns stamps."""
    if trajectory.kind == "random":
        return {"frame_rate_hz": str(FRAME_RATE_HZ), "stamp_rule": "frame index / frame_rate_hz seconds from 0"}
    return {"frame_rate_hz": repr(float(trajectory.rate_hz)),
            "stamp_rule": f"round(frame index * 1e9 / frame_rate_hz) ns from 0: the {trajectory.kind} survey's "
                          "time (trajectory.rate_hz)"}


def detection_box(box: tuple[int, int, int, int]) -> tuple[float, float, float, float]:
    """(cx, cy, size_x, size_y) in pixel-edge coordinates (pixel u covers [u, u + 1]) of a KITTI box (left, top,
    right, bottom) of inclusive pixel indices: cx = (left + right + 1) / 2, size_x = right - left + 1."""
    left, top, right, bottom = box
    return ((left + right + 1) / 2, (top + bottom + 1) / 2, float(right - left + 1), float(bottom - top + 1))


def _header(ns: int, frame_id: str = CAMERA_FRAME) -> dict:
    return {"stamp": {"sec": ns // NS_PER_S, "nanosec": ns % NS_PER_S}, "frame_id": frame_id}


def _require_mcap() -> Any:
    try:
        from mcap_ros2.writer import Writer
    except ImportError as err:
        raise ExportError(f"the mcap format needs the packages mcap and mcap-ros2-support ({err}); install them "
                          f"with: {INSTALL_HINT}") from None
    with BytesIO() as probe:  # the channel table _write fills (see _channel): refuse a writer without it up front
        w = Writer(probe)
        if not (hasattr(w, "_writer") and isinstance(getattr(w, "_channel_ids", None), dict)):
            raise ExportError("the mcap format: this mcap-ros2-support's Writer has no channel table to register "
                              f"channels with their QoS; install a supported one with: {INSTALL_HINT}")
    return Writer


def _channel(bag: Any, topic: str, schema: Any) -> None:
    """Register topic's channel with its offered_qos_profiles before its first message: mcap_ros2's Writer would
    register it on that message with no metadata (its writer and topic -> channel table: mcap-ros2-support 0.5-0.6,
    checked by _require_mcap)."""
    bag._channel_ids[topic] = bag._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema.id,
                                                           metadata=offered_qos(topic))


class McapExporter:
    """Every split gets its bag, with no messages if no frame fell in it."""

    needs_masks = False  # boxes come from label_2 (distractors' from the masks, which the reader adds then)
    folder_globs = ("*.mcap",)  # this export's bags, an earlier one's, and fetch --format mcap's per-shard bags

    def __init__(self) -> None:
        self._writer_class = _require_mcap()  # here, so a missing package stops the export before it starts
        self._info: ExportInfo | None = None
        self._files: dict[str, Any] = {}
        self._bags: dict[str, Any] = {}
        self._schemas: dict[str, dict[str, Any]] = {}
        self._frames: dict[str, int] = {}

    def frame_outputs(self, split: str, name: str) -> tuple[str, ...]:
        return ()  # no per-frame files: every frame goes into OUT/{split}.mcap

    def folder_outputs(self) -> tuple[str, ...]:
        return tuple(f"{split}.mcap" for split in SPLITS)

    def bag_path(self, split: str) -> Path:
        return self._info.out / f"{split}.mcap"

    def begin(self, info: ExportInfo) -> None:
        self._info = info
        make_dirs(info.out)
        for split in SPLITS:
            path = tmp_name(self.bag_path(split))
            try:
                f = self._files[split] = open(path, "wb")
            except OSError as err:
                self.abort()
                raise ExportError(f"{path}: cannot write ({err.strerror or err})") from None
            self._bags[split] = self._writer_class(f)
            self._schemas[split] = {}
            self._frames[split] = 0

    def _write(self, split: str, topic: str, message: dict, ns: int, sequence: int) -> None:
        schemas = self._schemas[split]
        if topic not in schemas:
            schemas[topic] = self._bags[split].register_msgdef(TOPICS[topic], msgdef(TOPICS[topic]))
            _channel(self._bags[split], topic, schemas[topic])
        self._bags[split].write_message(topic, schemas[topic], message, log_time=ns, publish_time=ns,
                                        sequence=sequence)

    def _distortion(self) -> list[float]:
        """CameraInfo's plumb_bob d: [k1, k2, p1, p2, k3] (ROS's order is OpenCV's), empty for none."""
        camera = self._info.camera
        return [] if camera is None or not any(camera["distortion"]) else list(camera["distortion"])

    def add(self, frame: Frame, split: str) -> None:
        ns, seq = stamp_ns(frame.index, self._info.trajectory), frame.index
        if self._frames[split] == 0:  # once a bag, with its first frame
            static = sensor_tf_static(lambda f: _header(ns, f), self._info.sensors)
            if static is not None:
                self._write(split, TF_STATIC_TOPIC, static, ns, seq)
        try:
            image = frame.image.read_bytes()
        except OSError as err:
            raise ExportError(f"{frame.image}: unreadable ({err.strerror or err})") from None
        # CompressedImage's format names the codec: png or jpeg, as outputs.image_format does
        self._write(split, IMAGE_TOPIC, {"header": _header(ns), "format": self._info.image_format, "data": image}, ns,
                    seq)

        p = camera_projection(frame.calib)
        self._write(split, INFO_TOPIC, {
            "header": _header(ns), "height": frame.height, "width": frame.width, "distortion_model": "plumb_bob",
            "d": self._distortion(), "k": p[:, :3].ravel().tolist(), "r": np.eye(3).ravel().tolist(),
            "p": p.ravel().tolist(),
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
        }, ns, seq)

        detections = []
        for k, obj in enumerate(frame.objects):  # label lines, then distractors in instance id order
            if obj.ignore:  # a DontCare region is no detection; the others keep their ids
                continue
            cx, cy, sx, sy = detection_box(obj.box)
            detections.append({
                "header": _header(ns),
                "results": [{"hypothesis": {"class_id": self._info.categories[obj.category], "score": 1.0},
                             "pose": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                               "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                                      "covariance": [0.0] * 36}}],
                "bbox": {"center": {"position": {"x": cx, "y": cy}, "theta": 0.0}, "size_x": sx, "size_y": sy},
                "id": str(k),  # the same with or without --distractors (instance ids need masks)
            })
        self._write(split, DETECTIONS_TOPIC, {"header": _header(ns), "detections": detections}, ns, seq)

        if frame.meta is not None:
            self._write(split, TF_TOPIC, camera_tf(lambda f: _header(ns, f), camera_pose(frame.meta)), ns, seq)

        if frame.depth is not None:
            depth = depth_metres(frame.depth, frame.width, frame.height)
            self._write(split, DEPTH_TOPIC, {
                "header": _header(ns), "height": frame.height, "width": frame.width, "encoding": "32FC1",
                "is_bigendian": 0, "step": frame.width * 4, "data": depth.astype("<f4").tobytes(),
            }, ns, seq)
        for topic, message in sensor_messages(frame.sensor_files, self._info.sensors, lambda f: _header(ns, f)):
            self._write(split, topic, message, ns, seq)
        self._frames[split] += 1

    def finish(self) -> None:
        info = self._info
        for split in SPLITS:
            bag = self._bags[split]
            bag.add_metadata("seasynth", {
                "format": "seasynth KITTI frames as a ROS 2 bag",
                **clock_metadata(info.trajectory),
                "split": split,
                "split_fractions": ",".join(repr(float(f)) for f in info.fractions),
                "frames": str(self._frames[split]),
                "categories": json.dumps(list(info.categories)),  # a JSON list: a class name may hold a comma
                "dataset_seed": str(info.dataset_seed),
                "spec_sha256": info.spec_sha256,
                "code_version": str(info.code_version),
                "camera_frame": f"{CAMERA_FRAME} (optical: x right, y down, z forward)",
                # the full camera model (port and distortion; seasynth.service.camera_model), where there is one
                **({} if info.camera is None else {"camera_model": json.dumps(info.camera, sort_keys=True)}),
            })
            bag.finish()
            path = self.bag_path(split)
            try:
                self._files.pop(split).close()
                os.replace(tmp_name(path), path)
            except OSError as err:
                raise ExportError(f"{path}: cannot write ({err.strerror or err})") from None
        self.abort()

    def abort(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()
        self._bags.clear()
        if self._info is not None:
            for split in SPLITS:
                tmp_name(self.bag_path(split)).unlink(missing_ok=True)
