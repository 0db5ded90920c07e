"""`seasynth export --format mcap` of a survey with every sonar and navigation sensor: each sensor message, decoded
with mcap-ros2's decoder, equals the dataset's fls/, fls_fan/, sss/ and nav/ files and the spec's sonar geometry."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.export import plan_export, run_export
from seasynth.worker.local.generate import generate
from seasynth.worker.scene.trajectory import GRAVITY
from seasynth.worker.sensors.fls import fls_grid
from seasynth.worker.sensors.sss import sss_grid

pytest.importorskip("mcap")
pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from seasynth.worker.export.mcap_sensors import DTYPE_UINT16, NOMINAL_SOUND_SPEED  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "survey-sonar.yaml"
SMALL = {"camera.width": 32, "camera.height": 24, "frames": 4, "shard_size": 2, "sensors.fls.beams": 16,
         "sensors.fls.range_bins": 24, "sensors.fls.horizontal_aperture_deg": 60.0, "sensors.fls.beam_width_deg": 4.0,
         "sensors.sss.enabled": True, "sensors.sss.range_bins": 16, "sensors.sss.horizontal_beam_deg": 2.0,
         # every sensor's pose its own: offsets, pitch and yaw that tell the sensors' frames apart
         "sensors.sss.pose.yaw_deg": -10.0, "sensors.dvl.pose.yaw_deg": 45.0,
         "sensors.pressure.pose.offset_m": [0.1, -0.4, 0.3],
         "sensors.imu.pose": {"offset_m": [0.05, -0.1, -0.2], "pitch_deg": 12.0, "yaw_deg": 25.0}}
SENSOR_TOPICS = ["/fls/image", "/fls/fan", "/fls/sonar_image", "/sss/image", "/sss/sonar_image", "/dvl/twist",
                 "/pressure", "/imu"]
F32 = np.float32


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    root = tmp_path_factory.mktemp("mcap-sensors")
    spec = load_spec(EXAMPLE, SMALL)
    generate(spec, root / "ds", workers=1)
    run_export(plan_export(root / "ds", "mcap", (1.0, 0.0, 0.0)), root / "out")
    with open(root / "out" / "train.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        messages = [(c.topic, s.name, m.log_time, d)
                    for s, c, m, d in reader.iter_decoded_messages(log_time_order=False)]
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return spec, root / "ds", messages, metadata


def png16(path: Path) -> np.ndarray:
    a = np.asarray(Image.open(path))
    assert a.dtype == np.uint16
    return a


def check_image(msg, a: np.ndarray, frame_id: str, ns: int) -> None:
    assert (msg.header.frame_id, msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) == (frame_id, ns)
    assert (msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step) == (*a.shape, "mono16", 0, 2 * a.shape[1])
    assert np.array_equal(np.frombuffer(bytes(msg.data), "<u2").reshape(a.shape), a)


def survey_ns(spec, i: int) -> int:
    """A survey's frame i is flown at i / rate_hz s (seasynth.worker.scene.trajectory); the bag stamps it there, in ns."""
    return round(i * 10**9 / spec.trajectory.rate_hz)


def test_survey_frames_are_stamped_at_their_time_on_the_survey(survey):
    spec, ds, messages, metadata = survey
    assert spec.trajectory.kind == "lawnmower" and spec.trajectory.rate_hz == 2.0
    assert {ns for _, _, ns, _ in messages} == {survey_ns(spec, i) for i in range(spec.frames)} \
        == {round(json.loads((ds / f"nav/{i:06d}.json").read_text())["time_s"] * 1e9) for i in range(spec.frames)}
    meta = metadata["seasynth"]
    assert (meta["frame_rate_hz"], meta["stamp_rule"]) == (
        "2.0", "round(frame index * 1e9 / frame_rate_hz) ns from 0: the lawnmower survey's time (trajectory.rate_hz)")
    # /tf moves at the speed /dvl/twist and nav/ say (along the first leg, world +x), not 5x faster
    tf = [(ns, m.transforms[0]) for t, _, ns, m in messages if t == "/tf"]
    assert [ns for ns, _ in tf] == [survey_ns(spec, i) for i in range(spec.frames)]
    for (ns0, a), (ns1, b) in zip(tf, tf[1:]):
        speed = (b.transform.translation.x - a.transform.translation.x) / ((ns1 - ns0) / 1e9)
        assert abs(speed - spec.trajectory.speed_m_s) < 1e-9
        assert b.header.stamp.sec * 10**9 + b.header.stamp.nanosec == ns1


def test_tf_static_places_each_sensor_where_meta_and_nav_put_it(survey):
    spec, ds, messages, _ = survey
    assert messages[0][0] == "/tf_static"  # once a bag, before anything else, with the first frame's stamp
    ((ns, static),) = [(ns, m) for t, _, ns, m in messages if t == "/tf_static"]
    assert ns == 0
    camera_from = {}
    for t in static.transforms:
        assert (t.header.frame_id, t.header.stamp.sec, t.header.stamp.nanosec) == ("camera", 0, 0)
        q, tr = t.transform.rotation, t.transform.translation
        assert q.w >= 0 and math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, abs_tol=1e-12)
        camera_from[t.child_frame_id] = np.eye(4)
        camera_from[t.child_frame_id][:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        camera_from[t.child_frame_id][:3, 3] = [tr.x, tr.y, tr.z]
    assert list(camera_from) == ["fls", "sss", "dvl", "pressure", "imu"]
    for name, T in camera_from.items():
        pose = getattr(spec.sensors, name).pose
        assert T[:3, 3].tolist() == list(pose.offset_m)
        # the documented convention: pitch tilts the forward axis down (+y), then yaw turns it to starboard (+x)
        p, y = math.radians(pose.pitch_deg), math.radians(pose.yaw_deg)
        forward = [math.sin(y) * math.cos(p), math.sin(p), math.cos(y) * math.cos(p)]
        assert np.abs(T[:3, 2] - forward).max() < 1e-12 and abs(T[1, 0]) < 1e-12  # x stays level
    for i in range(spec.frames):
        meta = json.loads((ds / f"meta/{i:06d}.json").read_text())
        nav = json.loads((ds / f"nav/{i:06d}.json").read_text())
        world_from_camera = np.array(meta["camera"]["pose_world_from_camera"])
        recorded = {"fls": meta["sensors"]["fls"]["pose_world_from_sonar"],
                    "sss": meta["sensors"]["sss"]["pose_world_from_sss"], "dvl": nav["dvl"]["pose_world_from_dvl"]}
        for name, world_from_sensor in recorded.items():
            assert np.abs(world_from_camera @ camera_from[name] - np.array(world_from_sensor)).max() < 1e-9, name
        # the pressure sensor reads the depth of its own origin; the IMU, specific force in its own axes
        z = (world_from_camera @ camera_from["pressure"])[2, 3]
        assert abs(nav["pressure"]["surface_z_world_m"] - z - nav["pressure"]["depth_true_m"]) < 1e-9
        r = world_from_camera[:3, :3] @ camera_from["imu"][:3, :3]
        force = r.T @ (np.array(nav["acceleration_world_m_s2"]) - GRAVITY)
        assert np.abs(force - nav["imu"]["specific_force_true_m_s2"]).max() < 1e-9


def test_every_sensor_message_equals_the_dataset_files(survey):
    spec, ds, messages, _ = survey
    fls, sss = spec.sensors.fls, spec.sensors.sss
    per_frame = {}
    for topic, schema, ns, msg in messages:
        per_frame.setdefault(ns, []).append((topic, schema, msg))
    assert sorted(per_frame) == [survey_ns(spec, i) for i in range(spec.frames)]
    for i in range(spec.frames):
        n, ns = f"{i:06d}", survey_ns(spec, i)
        got = [(t, s) for t, s, _ in per_frame[ns] if not t.startswith(("/camera", "/detections", "/tf"))]
        assert got == list(zip(SENSOR_TOPICS, ["sensor_msgs/msg/Image"] * 2
                               + ["marine_acoustic_msgs/msg/ProjectedSonarImage", "sensor_msgs/msg/Image",
                                  "marine_acoustic_msgs/msg/ProjectedSonarImage",
                                  "geometry_msgs/msg/TwistWithCovarianceStamped", "sensor_msgs/msg/FluidPressure",
                                  "sensor_msgs/msg/Imu"]))
        m = {t: msg for t, _, msg in per_frame[ns]}
        polar, fan, row = png16(ds / f"fls/{n}.png"), png16(ds / f"fls_fan/{n}.png"), png16(ds / f"sss/{n}.png")
        assert polar.shape == (24, 16) and row.shape == (1, 32)
        check_image(m["/fls/image"], polar, "fls", ns)
        check_image(m["/fls/fan"], fan, "fls", ns)
        check_image(m["/sss/image"], row, "sss", ns)

        sonar = m["/fls/sonar_image"]
        az = fls_grid(fls).beam_az  # the beam centres the echo model beamforms at
        assert [(d.x, d.y, d.z) for d in sonar.beam_directions] == [(math.sin(a), 0.0, math.cos(a)) for a in az]
        edges = fls_grid(fls).range_edges
        assert list(sonar.ranges) == [float(F32(r)) for r in (edges[:-1] + edges[1:]) / 2]
        p = sonar.ping_info
        assert (p.frequency, p.sound_speed) == (750_000.0, NOMINAL_SOUND_SPEED)
        assert list(p.tx_beamwidths) == [float(F32(math.radians(20.0)))] * 16
        assert list(p.rx_beamwidths) == [float(F32(math.radians(4.0)))] * 16
        img = sonar.image
        assert (img.dtype, img.beam_count, img.is_bigendian) == (DTYPE_UINT16, 16, False)
        assert np.array_equal(np.frombuffer(bytes(img.data), "<u2").reshape(24, 16), polar)

        side = m["/sss/sonar_image"]
        d = math.radians(sss.depression_deg)
        assert [(v.x, v.y, v.z) for v in side.beam_directions] == [(-math.cos(d), math.sin(d), 0.0),
                                                                   (math.cos(d), math.sin(d), 0.0)]
        e = sss_grid(sss).edges
        assert list(side.ranges) == [float(F32(r)) for r in (e[:-1] + e[1:]) / 2]
        assert (side.ping_info.frequency, side.image.beam_count) == (900_000.0, 2)
        cells = np.frombuffer(bytes(side.image.data), "<u2").reshape(16, 2)
        assert np.array_equal(cells[:, 0], row[0, :16][::-1]) and np.array_equal(cells[:, 1], row[0, 16:])

        nav = json.loads((ds / f"nav/{n}.json").read_text())
        tw = m["/dvl/twist"]
        assert tw.header.frame_id == "dvl"
        lin = tw.twist.twist.linear
        assert [lin.x, lin.y, lin.z] == nav["dvl"]["velocity_dvl_m_s"]
        s2 = spec.sensors.dvl.velocity_sigma_m_s ** 2
        assert list(tw.twist.covariance) == list(np.diag([s2, s2, s2, -1.0, -1.0, -1.0]).ravel())
        pr = m["/pressure"]
        assert (pr.header.frame_id, pr.fluid_pressure, pr.variance) == ("pressure", nav["pressure"]["pressure_pa"],
                                                                       100.0**2)
        imu = m["/imu"]
        w, a = imu.angular_velocity, imu.linear_acceleration
        assert [w.x, w.y, w.z] == nav["imu"]["angular_rate_rad_s"]
        assert [a.x, a.y, a.z] == nav["imu"]["specific_force_m_s2"]
        assert list(imu.orientation_covariance) == [-1.0] + [0.0] * 8
        assert list(imu.angular_velocity_covariance) == list(np.diag([1e-4**2] * 3).ravel())
        assert list(imu.linear_acceleration_covariance) == list(np.diag([1e-3**2] * 3).ravel())


def test_every_channel_offers_its_qos_and_tf_static_is_latched(survey):
    """rosbag2 plays each topic with the channel's offered_qos_profiles: /tf_static must be transient local (a
    listener joining after its one message still gets it), the others volatile, all reliable."""
    import yaml

    _, _, messages, _ = survey
    with open(survey[1].parent / "out" / "train.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    assert set(channels) == {t for t, *_ in messages}
    assert {"/tf_static", "/tf", "/camera/image/compressed", *SENSOR_TOPICS} <= set(channels)
    for topic, channel in channels.items():
        (qos,) = yaml.safe_load(channel.metadata["offered_qos_profiles"])
        assert qos["reliability"] == 1 and qos["history"] == 3, topic  # reliable; history as rosbag2 records it
        assert qos["durability"] == (1 if topic == "/tf_static" else 2), topic  # transient local / volatile
        assert qos["deadline"] == {"sec": 9223372036, "nsec": 854775807}, topic  # rmw's infinite duration
