"""`seasynth export`: COCO and YOLO files read back by their own tools equal the KITTI labels and instance masks."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from export_fixtures import FRACTIONS, SMALL, coco, datasets, yolo  # noqa: F401 (fixtures)
from local_datasets import tree
from PIL import Image

from seasynth.service.errors import ExportError
from seasynth.worker.export import (
    SPLITS,
    STREAM_SPLIT,
    ExportInfo,
    Frame,
    FrameObject,
    parse_split,
    plan_export,
    run_export,
    split_of,
)
from seasynth.worker.export.coco import coco_bbox, instance_runs, rle_counts, rle_string
from seasynth.worker.export.files import EXPORT_RECORD
from seasynth.worker.export.yolo import YoloExporter
from seasynth.worker.frame import kitti
from seasynth.worker.frame.labels import tight_boxes
from seasynth.worker.local.folder import RECORD

pycocotools = pytest.importorskip("pycocotools")
from pycocotools import mask as mask_utils  # noqa: E402
from pycocotools.coco import COCO  # noqa: E402

# pycocotools 2.0.11's decode trips numpy 2's copy-keyword deprecation; its output is unaffected.
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation doesn't accept a copy keyword")

def frame_truth(ds: Path, index: int) -> tuple[list[dict], np.ndarray, dict]:
    """(KITTI label lines, (h, w) int64 instance ids, meta) of one frame, read with the project's own parsers."""
    n = f"{index:06d}"
    lines = kitti.parse_label_file((ds / f"label_2/{n}.txt").read_text())
    instance = np.asarray(Image.open(ds / f"instance/{n}.png")).astype(np.int64)
    return lines, instance, json.loads((ds / f"meta/{n}.json").read_text())


def expected_splits(seed: int, frames: range, fractions) -> dict[int, str]:
    """The documented rule, written out again: u from SeedSequence([seed, i, STREAM_SPLIT]) vs cumulative sums."""
    out = {}
    for i in frames:
        u = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, i, STREAM_SPLIT]))).random()
        c = np.cumsum(fractions)
        out[i] = SPLITS[0] if u < c[0] else SPLITS[1] if u < c[1] else SPLITS[2]
    return out


# ------------------------------------------------------------------ COCO


def test_coco_files_load_and_every_annotation_is_its_kitti_line_and_instance_mask(datasets, coco):
    ds = datasets["masks"]
    seed = json.loads((ds / RECORD).read_text())["seed"]
    splits = expected_splits(seed, range(SMALL["frames"]), FRACTIONS)
    assert set(splits.values()) == set(SPLITS)  # the test covers all three
    seen, checked = set(), 0
    for split in SPLITS:
        api = COCO(str(coco / f"annotations/instances_{split}.json"))
        assert api.loadCats(api.getCatIds()) == [{"id": 1, "name": "Urchin", "supercategory": "target"}]
        ids = sorted(api.getImgIds())
        assert ids == sorted(i for i, s in splits.items() if s == split)
        assert sorted(p.name for p in (coco / "images" / split).iterdir()) == [f"{i:06d}.png" for i in ids]
        for i in ids:
            seen.add(i)
            n = f"{i:06d}"
            assert api.imgs[i] == {"id": i, "file_name": f"{n}.png", "width": 64, "height": 48}
            assert (coco / f"images/{split}/{n}.png").read_bytes() == (ds / f"image_2/{n}.png").read_bytes()
            lines, instance, meta = frame_truth(ds, i)
            id_of_line = {o["label_line"]: o["instance_id"] for o in meta["objects"] if o["label_line"] is not None}
            anns = api.loadAnns(api.getAnnIds(imgIds=[i]))
            assert [a["kitti_line"] for a in anns] == list(range(len(lines)))
            for a, line in zip(anns, lines):
                left, top, right, bottom = line["bbox"]
                assert a["bbox"] == [left, top, right - left + 1, bottom - top + 1]
                mask = instance == id_of_line[a["kitti_line"]]
                assert a["instance_id"] == id_of_line[a["kitti_line"]]
                decoded = mask_utils.decode(a["segmentation"])
                assert decoded.shape == (48, 64) and np.array_equal(decoded.astype(bool), mask)
                assert a["area"] == int(mask.sum()) == int(mask_utils.area(a["segmentation"]))
                assert list(mask_utils.toBbox(a["segmentation"])) == a["bbox"]
                assert (a["category_id"], a["iscrowd"]) == (1, 0)
                assert (a["truncated"], a["occluded"]) == (line["truncated"], line["occluded"])
                assert a["segmentation"]["counts"] == mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))[
                    "counts"].decode()
                checked += 1
    assert seen == set(range(SMALL["frames"])) and checked > 10
    assert not [p for p in coco.rglob("*") if ".tmp-" in p.name]
    record = json.loads((coco / EXPORT_RECORD).read_text())
    assert record["state"] == "complete" and record["masks"] == "instance/"


def test_coco_distractors_are_every_visible_distractor_with_its_tight_box(datasets, tmp_path):
    ds = datasets["masks"]
    run_export(plan_export(ds, "coco", (1.0, 0.0, 0.0), distractors=True), tmp_path)
    api = COCO(str(tmp_path / "annotations/instances_train.json"))
    assert [c["name"] for c in api.loadCats(api.getCatIds())] == ["Urchin", "distractor"]
    distractors = 0
    for i in range(SMALL["frames"]):
        lines, instance, meta = frame_truth(ds, i)
        boxes = tight_boxes(instance)
        anns = api.loadAnns(api.getAnnIds(imgIds=[i]))
        want = sorted(o["instance_id"] for o in meta["objects"] if o["role"] == "distractor" and o["instance_id"]
                      in boxes)
        got = [a for a in anns if a["category_id"] == 2]
        assert [a["instance_id"] for a in got] == want
        assert len(anns) == len(lines) + len(want)
        for a in got:
            b = boxes[a["instance_id"]]
            assert a["bbox"] == coco_bbox((b.left, b.top, b.right, b.bottom)) and a["area"] == b.pixels
            assert a["truncated"] is None and a["occluded"] is None and a["kitti_line"] is None
            assert np.array_equal(mask_utils.decode(a["segmentation"]).astype(bool), instance == a["instance_id"])
        distractors += len(got)
    assert distractors > 0
    assert [p.name for p in (tmp_path / "images/val").iterdir()] == []  # an empty split is empty, not absent
    assert COCO(str(tmp_path / "annotations/instances_val.json")).getImgIds() == []


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (48, 64), (7, 2)])
def test_rle_equals_pycocotools_encode(shape):
    rng = np.random.default_rng(list(shape))
    for density in (0.0, 0.1, 0.5, 0.9, 1.0):
        ids = (rng.random(shape) < density).astype(np.uint16) * rng.integers(1, 4, shape).astype(np.uint16)
        runs = instance_runs(ids)
        for iid in np.unique(ids[ids > 0]):
            mask = np.asfortranarray((ids == iid).astype(np.uint8))
            ours = rle_string(rle_counts(runs, int(iid), ids.size))
            assert ours == mask_utils.encode(mask)["counts"].decode()


# ------------------------------------------------------------------ YOLO

YOLO_NUMBER = r"(0|1|0?\.\d+|1\.0*|\d\.\d+(e-?\d+)?)"
YOLO_LINE = re.compile(rf"^(\d+) {YOLO_NUMBER} {YOLO_NUMBER} {YOLO_NUMBER} {YOLO_NUMBER}$")


def read_yolo_labels(path: Path, classes: int) -> list[tuple[int, float, float, float, float]]:
    """Ultralytics' documented detection format, strictly: one `class x_center y_center width height` row per
    object, class zero-indexed, coordinates normalised to [0, 1], the box inside the image, no duplicate rows."""
    text = path.read_text()
    assert text == "" or text.endswith("\n"), path
    rows = []
    for line in text.splitlines():
        m = YOLO_LINE.match(line)
        assert m, f"{path}: not a YOLO row: {line!r}"
        cls, *xywh = line.split(" ")
        cx, cy, w, h = map(float, xywh)
        assert 0 <= int(cls) < classes and all(math.isfinite(v) and 0 <= v <= 1 for v in (cx, cy, w, h))
        assert w > 0 and h > 0 and cx - w / 2 >= -1e-12 and cx + w / 2 <= 1 + 1e-12, line
        rows.append((int(cls), cx, cy, w, h))
    assert len(set(rows)) == len(rows), f"{path}: duplicate rows"
    return rows


def test_yolo_rows_round_trip_to_the_kitti_boxes(datasets, yolo):
    ds = datasets["masks"]
    data = yaml.safe_load((yolo / "data.yaml").read_text())
    assert data == {"path": str(yolo.absolute()), "train": "images/train", "val": "images/val",
                    "test": "images/test", "names": {0: "Urchin"}}
    seed = json.loads((ds / RECORD).read_text())["seed"]
    splits = expected_splits(seed, range(SMALL["frames"]), FRACTIONS)
    rows_checked = 0
    for split in SPLITS:
        images = sorted(p.name for p in (yolo / "images" / split).iterdir())
        assert images == [f"{i:06d}.png" for i, s in splits.items() if s == split]
        assert sorted(p.name for p in (yolo / "labels" / split).iterdir()) == [n[:-4] + ".txt" for n in images]
        for name in images:
            stem = name[:-4]
            lines = kitti.parse_label_file((ds / f"label_2/{stem}.txt").read_text())
            rows = read_yolo_labels(yolo / f"labels/{split}/{stem}.txt", classes=1)
            assert len(rows) == len(lines)
            for (cls, cx, cy, w, h), line in zip(rows, lines):
                # Pixel edges back: [cx - w/2, cx + w/2] * width = [left, right + 1].
                edges = np.array([(cx - w / 2) * 64, (cy - h / 2) * 48, (cx + w / 2) * 64 - 1, (cy + h / 2) * 48 - 1])
                assert cls == 0
                assert np.abs(edges - np.array(line["bbox"])).max() < 1e-6
                rows_checked += 1
    assert rows_checked > 10


def test_yolo_frame_without_objects_gets_an_empty_label_file(tmp_path):
    exporter = YoloExporter()
    exporter.begin(ExportInfo(out=tmp_path, categories=("Urchin",), width=8, height=8, dataset_seed=0,
                              spec_sha256="0" * 64, code_version="x", fractions=(1.0, 0.0, 0.0)))
    image = tmp_path / "src.png"
    image.write_bytes(b"png bytes")
    exporter.add(Frame(index=5, name="000005", image=image, width=8, height=8, objects=(), instance=None), "val")
    one = FrameObject(category=0, box=(0, 0, 7, 7), instance_id=None, pixels=None, truncated=0.0, occluded=0,
                      label_line=0)
    exporter.add(Frame(index=6, name="000006", image=image, width=8, height=8, objects=(one,), instance=None), "val")
    assert (tmp_path / "labels/val/000005.txt").read_bytes() == b""
    assert (tmp_path / "labels/val/000006.txt").read_text() == "0 0.5000000000 0.5000000000 1.0000000000 1.0000000000\n"
    assert (tmp_path / "images/val/000005.png").read_bytes() == b"png bytes"


def test_yolo_with_distractors_labels_them_as_class_1(datasets, tmp_path):
    ds = datasets["masks"]
    run_export(plan_export(ds, "yolo", (1.0, 0.0, 0.0), distractors=True), tmp_path)
    assert yaml.safe_load((tmp_path / "data.yaml").read_text())["names"] == {0: "Urchin", 1: "distractor"}
    for i in range(SMALL["frames"]):
        lines, instance, meta = frame_truth(ds, i)
        boxes = tight_boxes(instance)
        rows = read_yolo_labels(tmp_path / f"labels/train/{i:06d}.txt", classes=2)
        want = [boxes[o["instance_id"]] for o in sorted(meta["objects"], key=lambda o: o["instance_id"])
                if o["role"] == "distractor" and o["instance_id"] in boxes]
        assert [r[0] for r in rows] == [0] * len(lines) + [1] * len(want)
        for (_, cx, cy, w, h), b in zip(rows[len(lines):], want):
            edges = [(cx - w / 2) * 64, (cy - h / 2) * 48, (cx + w / 2) * 64 - 1, (cy + h / 2) * 48 - 1]
            assert np.abs(np.array(edges) - [b.left, b.top, b.right, b.bottom]).max() < 1e-6


# ------------------------------------------------------------------ split, determinism, idempotence


def test_split_rule_is_the_documented_pure_function():
    frames = range(2000)
    for fractions in ((0.8, 0.1, 0.1), (0.5, 0.25, 0.25), (0.3, 0.0, 0.7)):
        want = expected_splits(42, frames, fractions)
        got = {i: SPLITS[split_of(42, i, fractions)] for i in frames}
        assert got == want
        shares = [sum(s == name for s in got.values()) / len(frames) for name in SPLITS]
        assert np.allclose(shares, fractions, atol=0.04)
    assert {split_of(42, i, (0.0, 1.0, 0.0)) for i in frames} == {1}
    # Sums that round below 1 still put every frame in a split of nonzero fraction.
    assert {split_of(3, i, (0.7, 0.3, 0.0)) for i in frames} == {0, 1}


@pytest.mark.parametrize("text", ["0.5,0.5", "0.7,0.2,0.2", "a,b,c", "-0.1,0.6,0.5", "nan,0.5,0.5", "1,0,0,0"])
def test_bad_split_is_refused(text):
    with pytest.raises(ExportError, match="split"):
        parse_split(text)


def test_parse_split_accepts_fractions_summing_to_one_after_rounding():
    assert parse_split("0.8,0.1,0.1") == (0.8, 0.1, 0.1)
    assert parse_split(" 1 , 0 , 0 ") == (1.0, 0.0, 0.0)


@pytest.mark.parametrize("fmt", ["coco", "yolo"])
def test_export_does_not_depend_on_how_the_dataset_was_generated(datasets, fmt, coco, yolo, tmp_path):
    run_export(plan_export(datasets["masks2"], fmt, FRACTIONS), tmp_path)
    ours, theirs = tree(tmp_path), tree(coco if fmt == "coco" else yolo)
    if fmt == "yolo":  # data.yaml names its own folder
        ours.pop("data.yaml"), theirs.pop("data.yaml")
    assert ours == theirs


@pytest.mark.parametrize("fmt", ["coco", "yolo"])
def test_export_twice_and_over_another_split_gives_the_same_bytes(datasets, fmt, coco, yolo, tmp_path):
    first = coco if fmt == "coco" else yolo
    out = tmp_path / "out"
    shutil.copytree(first, out)
    run_export(plan_export(datasets["masks"], fmt, FRACTIONS), out)
    a, b = tree(out), tree(first)
    if fmt == "yolo":  # data.yaml names its own folder
        assert a.pop("data.yaml") == b.pop("data.yaml").replace(str(first).encode(), str(out).encode())
    assert a == b
    # Over an export of another split (files in other folders) and a crash's leftovers: the same tree again.
    run_export(plan_export(datasets["masks"], fmt, (0.1, 0.1, 0.8)), out)
    (out / "images/train/.000000.png.tmp-99").write_bytes(b"partial")
    fresh = tmp_path / "fresh"
    run_export(plan_export(datasets["masks"], fmt, FRACTIONS), out)
    run_export(plan_export(datasets["masks"], fmt, FRACTIONS), fresh)
    a, b = tree(out), tree(fresh)
    if fmt == "yolo":
        a.pop("data.yaml"), b.pop("data.yaml")
    assert a == b


def test_a_crash_leaves_the_export_marked_incomplete_and_no_temporary_files(datasets, tmp_path, monkeypatch):
    from seasynth.worker.export.dataset import FrameReader

    read = FrameReader.read

    def failing(self, index):
        if index == 5:
            raise RuntimeError("crash")
        return read(self, index)

    monkeypatch.setattr(FrameReader, "read", failing)
    with pytest.raises(RuntimeError, match="crash"):
        run_export(plan_export(datasets["masks"], "coco", FRACTIONS), tmp_path)
    assert json.loads((tmp_path / EXPORT_RECORD).read_text())["state"] == "incomplete"
    assert not (tmp_path / "annotations/instances_train.json").exists()
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name]
