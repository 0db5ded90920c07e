"""`seasynth export --format mcap`: ROS 2 bags read back with mcap's reader and mcap-ros2's decoder equal the KITTI
image, calib, label, depth and meta files, message by message."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from seasynth.service.errors import ExportError
from seasynth.worker.export import SPLITS, plan_export, run_export, split_of
from seasynth.worker.export.files import EXPORT_RECORD
from seasynth.worker.frame import kitti
from seasynth.worker.local.folder import RECORD

pytest.importorskip("mcap")
pytest.importorskip("mcap_ros2")
from local_datasets import generate_variants, seasynth, tree  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from seasynth.worker.export.mcap import FRAME_RATE_HZ, detection_box  # noqa: E402

SMALL = {"camera.width": 64, "camera.height": 48, "frames": 8}
FRACTIONS = (0.5, 0.25, 0.25)
TOPICS = {
    "/camera/image/compressed": "sensor_msgs/msg/CompressedImage",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/detections": "vision_msgs/msg/Detection2DArray",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/camera/depth": "sensor_msgs/msg/Image",
}


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    """The same frames with depth/ and without."""
    return generate_variants(tmp_path_factory.mktemp("datasets"), SMALL,
                             {"depth": ({"outputs.depth": True}, 1), "plain": ({}, 1)})


@pytest.fixture(scope="module")
def bags(datasets, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("mcap") / "out"
    run_export(plan_export(datasets["depth"], "mcap", FRACTIONS), out)
    return out


def read_bag(path: Path) -> tuple[dict, list[tuple]]:
    """(summary facts, [(topic, schema name, log_time, publish_time, sequence, decoded message)] in file order)."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        messages = [(channel.topic, schema.name, message.log_time, message.publish_time, message.sequence, decoded)
                    for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False)]
        encodings = {(c.topic, c.message_encoding, summary.schemas[c.schema_id].encoding)
                     for c in summary.channels.values()}
    return {"profile": header.profile, "metadata": metadata, "encodings": encodings}, messages


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def kitti_depth(path: Path) -> np.ndarray:
    raw = np.asarray(Image.open(path)).astype(np.float64)
    return np.where(raw == 0, np.nan, raw / 256.0)


def check_header(header, index: int, frame_id: str = "camera") -> None:
    ns = index * 10**9 // FRAME_RATE_HZ
    assert ns == round(index / FRAME_RATE_HZ * 1e9)
    assert (header.stamp.sec, header.stamp.nanosec) == (ns // 10**9, ns % 10**9)
    assert header.frame_id == frame_id


def check_bags(ds: Path, out: Path, *, depth: bool) -> int:
    """Every message of every bag against the dataset's files; returns the number of frames checked."""
    seed = json.loads((ds / RECORD).read_text())["seed"]
    class_name = json.loads((ds / RECORD).read_text())["spec"]["targets"]["class_name"]
    topics = {t: s for t, s in TOPICS.items() if depth or t != "/camera/depth"}
    assert sorted(p.name for p in out.iterdir()) == sorted([*(f"{s}.mcap" for s in SPLITS), EXPORT_RECORD])
    assert json.loads((out / EXPORT_RECORD).read_text())["format"] == "mcap"
    checked = 0
    for split in SPLITS:
        want = [i for i in range(SMALL["frames"]) if SPLITS[split_of(seed, i, FRACTIONS)] == split]
        facts, messages = read_bag(out / f"{split}.mcap")
        assert facts["profile"] == "ros2"
        meta = facts["metadata"]["seasynth"]
        assert (meta["frame_rate_hz"], meta["split"], meta["frames"]) == (str(FRAME_RATE_HZ), split, str(len(want)))
        assert json.loads(meta["categories"]) == [class_name]
        assert facts["encodings"] == ({(t, "cdr", "ros2msg") for t in topics} if want else set())
        # Frames in ascending index, each with one message per topic, in the topics' order.
        assert [(m[0], m[1]) for m in messages] == [(t, s) for _ in want for t, s in topics.items()]
        for k, i in enumerate(want):
            n = f"{i:06d}"
            ns = i * 10**9 // FRAME_RATE_HZ
            frame = {m[0]: m for m in messages[k * len(topics):(k + 1) * len(topics)]}
            for topic, (_, _, log_time, publish_time, sequence, _) in frame.items():
                assert (log_time, publish_time, sequence) == (ns, ns, i), topic

            image = frame["/camera/image/compressed"][5]
            check_header(image.header, i)
            assert image.format == "png"
            assert bytes(image.data) == (ds / f"image_2/{n}.png").read_bytes()

            info = frame["/camera/camera_info"][5]
            check_header(info.header, i)
            p2 = kitti.parse_calib((ds / f"calib/{n}.txt").read_text())["P2"]
            assert (info.width, info.height) == (SMALL["camera.width"], SMALL["camera.height"])
            assert list(info.k) == p2[:, :3].ravel().tolist()
            assert list(info.p) == np.hstack([p2[:, :3], np.zeros((3, 1))]).ravel().tolist() == p2.ravel().tolist()
            assert list(info.r) == np.eye(3).ravel().tolist()
            assert list(info.d) == [] and info.distortion_model == "plumb_bob"

            dets = frame["/detections"][5]
            check_header(dets.header, i)
            lines = kitti.parse_label_file((ds / f"label_2/{n}.txt").read_text())
            assert len(dets.detections) == len(lines)
            for line_no, (det, line) in enumerate(zip(dets.detections, lines)):
                check_header(det.header, i)
                left, top, right, bottom = line["bbox"]
                assert (det.bbox.center.position.x, det.bbox.center.position.y, det.bbox.size_x,
                        det.bbox.size_y) == ((left + right + 1) / 2, (top + bottom + 1) / 2, right - left + 1,
                                             bottom - top + 1)
                # and back: the pixel-edge box gives the inclusive KITTI box exactly
                cx, cy, sx, sy = det.bbox.center.position.x, det.bbox.center.position.y, det.bbox.size_x, \
                    det.bbox.size_y
                assert (cx - sx / 2, cy - sy / 2, cx + sx / 2 - 1, cy + sy / 2 - 1) == (left, top, right, bottom)
                assert det.bbox.center.theta == 0.0
                assert [(r.hypothesis.class_id, r.hypothesis.score) for r in det.results] == [(class_name, 1.0)]
                assert line["type"] == class_name
                assert det.id == str(line_no)
            checked += bool(lines)

            tf = frame["/tf"][5]
            assert len(tf.transforms) == 1
            t = tf.transforms[0]
            check_header(t.header, i, "world")
            assert t.child_frame_id == "camera"
            pose = np.array(json.loads((ds / f"meta/{n}.json").read_text())["camera"]["pose_world_from_camera"])
            tr, q = t.transform.translation, t.transform.rotation
            assert [tr.x, tr.y, tr.z] == pose[:3, 3].tolist()
            assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, abs_tol=1e-12) and q.w >= 0
            assert np.abs(quaternion_matrix(q.x, q.y, q.z, q.w) - pose[:3, :3]).max() < 1e-9

            if depth:
                img = frame["/camera/depth"][5]
                check_header(img.header, i)
                assert (img.encoding, img.is_bigendian, img.width, img.height, img.step) == (
                    "32FC1", 0, SMALL["camera.width"], SMALL["camera.height"], SMALL["camera.width"] * 4)
                got = np.frombuffer(bytes(img.data), dtype="<f4").reshape(img.height, img.width)
                truth = kitti_depth(ds / f"depth/{n}.png")
                assert np.array_equal(np.isnan(got), np.isnan(truth))
                assert np.array_equal(got[~np.isnan(got)].astype(np.float64), truth[~np.isnan(truth)])
    return checked


def test_every_message_equals_the_kitti_and_meta_files(datasets, bags):
    seed = json.loads((datasets["depth"] / RECORD).read_text())["seed"]
    assert {SPLITS[split_of(seed, i, FRACTIONS)] for i in range(SMALL["frames"])} == set(SPLITS)  # all three
    with_objects = check_bags(datasets["depth"], bags, depth=True)
    assert with_objects > 0  # some frame has detections to compare
    assert any((datasets["depth"] / "depth").iterdir())


def test_a_dataset_without_depth_has_no_depth_topic(datasets, tmp_path):
    run_export(plan_export(datasets["plain"], "mcap", FRACTIONS), tmp_path)
    check_bags(datasets["plain"], tmp_path, depth=False)


def test_export_twice_gives_the_same_bytes(datasets, bags, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(bags, out)
    run_export(plan_export(datasets["depth"], "mcap", FRACTIONS), out)  # over the first
    fresh = tmp_path / "fresh"
    run_export(plan_export(datasets["depth"], "mcap", FRACTIONS), fresh)
    assert tree(out) == tree(bags) == tree(fresh)
    assert not [p for p in out.rglob("*") if ".tmp-" in p.name]


def test_an_empty_split_gets_a_bag_without_messages(datasets, tmp_path):
    run_export(plan_export(datasets["plain"], "mcap", (1.0, 0.0, 0.0)), tmp_path)
    for split in ("val", "test"):
        facts, messages = read_bag(tmp_path / f"{split}.mcap")
        assert messages == [] and facts["metadata"]["seasynth"]["frames"] == "0"
    _, messages = read_bag(tmp_path / "train.mcap")
    assert sorted({m[4] for m in messages}) == list(range(SMALL["frames"]))


def detection_rows(msg) -> list[tuple]:
    """(id, class, score, cx, cy, size_x, size_y) of each Detection2D of a Detection2DArray."""
    return [(d.id, d.results[0].hypothesis.class_id, d.results[0].hypothesis.score, d.bbox.center.position.x,
             d.bbox.center.position.y, d.bbox.size_x, d.bbox.size_y) for d in msg.detections]


def test_distractors_follow_the_targets_whose_detections_and_ids_stay_as_without(datasets, tmp_path):
    ds = datasets["plain"]
    run_export(plan_export(ds, "mcap", FRACTIONS), tmp_path / "plain")
    run_export(plan_export(ds, "mcap", FRACTIONS, distractors=True), tmp_path / "dist")
    seen = frames = 0
    for split in SPLITS:
        plain = {m[4]: detection_rows(m[5]) for m in read_bag(tmp_path / "plain" / f"{split}.mcap")[1]
                 if m[0] == "/detections"}
        for topic, _, _, _, i, msg in read_bag(tmp_path / "dist" / f"{split}.mcap")[1]:
            if topic != "/detections":
                continue
            lines = kitti.parse_label_file((ds / f"label_2/{i:06d}.txt").read_text())
            rows = detection_rows(msg)
            # id = the detection's place in the array, with or without distractors: a target's is its label line
            assert [r[0] for r in rows] == [str(k) for k in range(len(rows))]
            assert rows[:len(lines)] == plain[i]
            assert [r[1] for r in rows] == [line["type"] for line in lines] + ["distractor"] * (len(rows) - len(lines))
            seen += len(rows) - len(lines)
            frames += 1
    assert frames == SMALL["frames"] and seen > 0


def test_survey_stamps_round_the_time_of_flight_and_random_frames_keep_the_nominal_rate():
    from seasynth.service.spec.sensors import Trajectory
    from seasynth.worker.export.mcap import stamp_ns

    three = Trajectory(kind="lawnmower", rate_hz=3.0)
    assert [stamp_ns(i, three) for i in range(4)] == [0, 333_333_333, 666_666_667, 1_000_000_000]
    assert stamp_ns(999_999, Trajectory(kind="lawnmower", rate_hz=0.01)) == 99_999_900 * 10**9
    assert [stamp_ns(i, Trajectory()) for i in (0, 1, 7)] == [0, 100_000_000, 700_000_000]


def test_metadata_lists_the_categories_as_json_whatever_their_characters(tmp_path):
    from seasynth.worker.export import ExportInfo
    from seasynth.worker.export.mcap import McapExporter

    exporter = McapExporter()
    exporter.begin(ExportInfo(out=tmp_path, categories=("Sea,urchin", "distractor"), width=8, height=8,
                              dataset_seed=0, spec_sha256="0" * 64, code_version="x", fractions=(1.0, 0.0, 0.0)))
    exporter.finish()
    for split in SPLITS:
        meta = read_bag(tmp_path / f"{split}.mcap")[0]["metadata"]["seasynth"]
        assert json.loads(meta["categories"]) == ["Sea,urchin", "distractor"]


def test_detection_box_is_the_pixel_edge_box():
    assert detection_box((0, 0, 0, 0)) == (0.5, 0.5, 1.0, 1.0)
    assert detection_box((3, 5, 10, 6)) == (7.0, 6.0, 8.0, 2.0)


def test_missing_packages_are_named_with_the_install_command(datasets, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mcap_ros2.writer", None)
    with pytest.raises(ExportError, match=r"pip install -e '\.\[export\]'"):
        plan_export(datasets["plain"], "mcap", FRACTIONS)


def test_a_writer_without_the_channel_table_is_refused_before_any_work(datasets, monkeypatch):
    """Channels are registered with their QoS through mcap_ros2's Writer's channel table: a version without it is
    refused up front (naming the install command), not written without QoS."""
    import mcap_ros2.writer

    class Other:
        def __init__(self, output):
            self._writer = object()

    monkeypatch.setattr(mcap_ros2.writer, "Writer", Other)
    with pytest.raises(ExportError, match=r"no channel table .* pip install -e '\.\[export\]'"):
        plan_export(datasets["plain"], "mcap", FRACTIONS)


def test_cli_exports_mcap(datasets, tmp_path):
    r = seasynth("export", datasets["plain"], "--format", "mcap", "--out", tmp_path / "cli", "--split", "0.5,0.25,0.25")
    assert r.returncode == 0, r.stderr
    assert "mcap export of 8 frames" in r.stdout
    check_bags(datasets["plain"], tmp_path / "cli", depth=False)


def test_rotation_quaternion_round_trips_on_every_branch():
    from seasynth.worker.export.mcap_tf import rotation_quaternion

    rng = np.random.default_rng(7)
    rotations = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]),
                 np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])]
    for _ in range(200):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rotations.append(q * np.sign(np.linalg.det(q)))
    for r in rotations:
        x, y, z, w = rotation_quaternion(r)
        assert w >= 0 and math.isclose(x * x + y * y + z * z + w * w, 1.0, abs_tol=1e-12)
        assert np.abs(quaternion_matrix(x, y, z, w) - r).max() < 1e-12
