"""Every output of a multi-class dataset carries each object's class, and the label filters turn the targets below
them into regions to ignore: over random seeds and filters, generated locally with every export, each label box is
the tight box of its instance's pixels with its class right in KITTI, COCO, YOLO, MCAP and semantic/, and each
target below the filters is a KITTI DontCare line and a COCO iscrowd annotation, absent from YOLO and MCAP."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from seasynth.service.spec.dataset import DatasetSpec, parse_spec
from seasynth.worker.export import export_generated
from seasynth.worker.export.coco import coco_bbox
from seasynth.worker.export.yolo import yolo_line
from seasynth.worker.frame import kitti
from seasynth.worker.frame.labels import tight_boxes
from seasynth.worker.local.generate import generate

pytest.importorskip("pycocotools")
pytest.importorskip("mcap_ros2")
from pycocotools import mask as coco_mask
from test_export_mcap import read_bag

FRAMES = 3
# Three classes, one of each placement (the water class in schools), seen close enough to have boxes of all sizes.
THREE_CLASSES = {
    "frames": FRAMES, "quality": "draft", "camera": {"width": 128, "height": 96},
    "terrain": {"cells": 32, "variants": 2}, "materials": {"procedural": False},
    "targets": [
        {"class_name": "Urchin", "assets": [{"procedural": "urchin", "variants": 2}], "count": [2, 4],
         "scale": [1.5, 2.5]},
        {"class_name": "Debris", "assets": [{"procedural": "rock", "variants": 2}], "count": [1, 3],
         "scale": [3.0, 5.0], "placement": {"kind": "buried", "sunk_fraction": [0.2, 0.6]}},
        {"class_name": "Fish", "assets": [{"procedural": "clam", "variants": 2}], "count": [1, 2],
         "scale": [1.5, 2.5], "placement": {"kind": "water", "height_m": [0.1, 0.6], "school": {"size": [1, 3]}}},
    ],
    "distractors": {"count": [1, 3]},
    "water": {"solved_column": False},  # the classes' outputs, not the light: the closed form spares column solves
    "outputs": {"instance": True, "semantic": True, "coco": True, "yolo": True, "mcap": True,
                "split": [1.0, 0.0, 0.0]},
}


KINDS = ("urchin", "rock", "coral", "seaweed", "clam")


def three_class_spec(seed: int, min_px: int = 1, min_fraction: float = 0.0,
                     kinds: tuple[str, ...] = ("urchin", "rock", "clam")) -> DatasetSpec:
    """THREE_CLASSES with this seed and these filters, the classes drawing from these procedural kinds."""
    targets = [{**c, "assets": [{"procedural": kind, "variants": 2}]}
               for c, kind in zip(THREE_CLASSES["targets"], kinds)]
    return parse_spec({**THREE_CLASSES, "seed": seed, "targets": targets,
                       "labels": {"min_visible_px": min_px, "min_visible_fraction": min_fraction}})


def png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path))


def check_dataset(out: Path, spec: DatasetSpec) -> dict[str, int]:
    """Check every frame's files against its instance image and meta; counts of what was seen."""
    names = spec.class_names
    coco = json.loads((out / "export/coco/annotations/instances_train.json").read_text())
    assert [(c["id"], c["name"]) for c in coco["categories"]] == [(k + 1, n) for k, n in enumerate(names)]
    anns = {(a["image_id"], a["instance_id"]): a for a in coco["annotations"]}
    import yaml

    assert yaml.safe_load((out / "export/yolo/data.yaml").read_text())["names"] == dict(enumerate(names))
    _, messages = read_bag(out / "export/mcap/train.mcap")
    detections = {m[4]: m[5] for m in messages if m[0] == "/detections"}
    seen = {"labelled": 0, "ignored": 0, "classes": set()}
    lo = spec.labels
    for i in range(FRAMES):
        n = f"{i:06d}"
        instance = png(out / f"instance/{n}.png")
        boxes = tight_boxes(instance)
        meta = json.loads((out / f"meta/{n}.json").read_text())
        by_id = {o["instance_id"]: o for o in meta["objects"]}
        lines = kitti.parse_label_file((out / f"label_2/{n}.txt").read_text())
        # The semantic image is the instance image mapped through each object's class (distractors 0).
        lut = np.zeros(max(by_id) + 1 if by_id else 1, np.uint8)
        for iid, o in by_id.items():
            lut[iid] = names.index(o["class"]) + 1 if o["role"] == "target" else 0
        semantic = png(out / f"semantic/{n}.png")
        assert semantic.dtype == np.uint8 and np.array_equal(semantic, lut[instance])
        # Every target with a visible pixel has exactly one line, in instance-id order.
        visible = [iid for iid in sorted(boxes) if by_id[iid]["role"] == "target"]
        assert [o["instance_id"] for o in sorted(by_id.values(), key=lambda o: o["label_line"] or 0)
                if o["label_line"] is not None] == visible
        yolo = (out / f"export/yolo/labels/train/{n}.txt").read_text().splitlines()
        dets = list(detections[i].detections)
        yolo_expected, det_expected = [], []
        for k, line in enumerate(lines):
            (iid,) = [j for j, o in by_id.items() if o["label_line"] == k]
            o, box = by_id[iid], boxes[iid]
            assert tuple(line["bbox"]) == (box.left, box.top, box.right, box.bottom)
            assert o["visible_pixels"] == box.pixels and o["pixels_alone"] >= box.pixels
            passes = box.pixels >= lo.min_visible_px and box.pixels >= lo.min_visible_fraction * o["pixels_alone"]
            ann = anns[(i, iid)]
            assert ann["category_id"] == names.index(o["class"]) + 1
            assert ann["bbox"] == coco_bbox((box.left, box.top, box.right, box.bottom)) and ann["area"] == box.pixels
            rle = ann["segmentation"]
            assert np.array_equal(coco_mask.decode({"size": rle["size"], "counts": rle["counts"].encode()}),
                                  (instance == iid).astype(np.uint8))
            if passes:
                assert line["type"] == o["class"] and ann["iscrowd"] == 0
                yolo_expected.append(yolo_line(names.index(o["class"]), (box.left, box.top, box.right, box.bottom),
                                               spec.camera.width, spec.camera.height))
                det_expected.append((str(k), o["class"], (box.left + box.right + 1) / 2))
                seen["labelled"] += 1
                seen["classes"].add(o["class"])
            else:  # a region to ignore: KITTI's DontCare line, COCO's crowd annotation with its mask
                assert line["type"] == "DontCare" and ann["iscrowd"] == 1
                assert (line["truncated"], line["occluded"], line["alpha"], line["rotation_y"]) == (-1, -1, -10, -10)
                assert line["dimensions"] == [-1, -1, -1] and line["location"] == [-1000, -1000, -1000]
                seen["ignored"] += 1
        assert len(anns) == sum(1 for key in anns if key[0] < FRAMES)
        assert sum(1 for key in anns if key[0] == i) == len(lines)
        assert yolo == yolo_expected
        assert [(d.id, d.results[0].hypothesis.class_id, d.bbox.center.position.x) for d in dets] == det_expected
        # meta counts each class's objects drawn and left out; the rest are its objects.
        assert [c["class"] for c in meta["targets"]] == list(names)
        for c in meta["targets"]:
            assert c["drawn"] - c["left_out"] == sum(o["class"] == c["class"] for o in by_id.values())
    return seen


@pytest.fixture(scope="module")
def unfiltered(tmp_path_factory) -> tuple[Path, DatasetSpec]:
    out = tmp_path_factory.mktemp("classes") / "ds"
    spec = three_class_spec(5)
    generate(spec, out, workers=1)
    export_generated(out)
    return out, spec


def test_a_three_class_dataset_names_every_class_in_every_output(unfiltered):
    out, spec = unfiltered
    seen = check_dataset(out, spec)
    assert seen["ignored"] == 0 and seen["labelled"] >= 6 and seen["classes"] == set(spec.class_names)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(seed=st.integers(0, 1000), min_px=st.integers(1, 80), min_fraction=st.floats(0.0, 1.0),
       kinds=st.permutations(KINDS))
def test_targets_below_the_label_filters_are_regions_to_ignore_in_every_format(tmp_path_factory, seed, min_px,
                                                                               min_fraction, kinds):
    out = tmp_path_factory.mktemp("filtered") / "ds"
    spec = three_class_spec(seed, min_px, min_fraction, tuple(kinds[:3]))
    generate(spec, out, workers=1)
    export_generated(out)
    check_dataset(out, spec)


def test_the_filters_change_only_label_lines_coco_and_the_detections(unfiltered, tmp_path):
    """The same frames, filtered: images, instance, semantic, calib and meta keep their bytes (the meta's
    label_line still names each line); only the targets below the filters turn into DontCare lines."""
    out, _ = unfiltered
    filtered = tmp_path / "ds"
    generate(three_class_spec(5, min_px=30, min_fraction=0.5), filtered, workers=1)
    seen = 0
    for i in range(FRAMES):
        n = f"{i:06d}"
        for part in (f"image_2/{n}.png", f"instance/{n}.png", f"semantic/{n}.png", f"calib/{n}.txt",
                     f"meta/{n}.json"):
            assert (out / part).read_bytes() == (filtered / part).read_bytes(), part
        before = kitti.parse_label_file((out / f"label_2/{n}.txt").read_text())
        after = kitti.parse_label_file((filtered / f"label_2/{n}.txt").read_text())
        assert [b["bbox"] for b in before] == [a["bbox"] for a in after]
        assert all(a == b or a["type"] == "DontCare" for a, b in zip(after, before))
        seen += sum(a["type"] == "DontCare" for a in after)
    assert seen >= 1


def test_the_preview_counts_label_lines_per_class(unfiltered, tmp_path):
    from seasynth.worker.preview.sheet import make_preview

    out, _ = unfiltered
    lines = [line.split()[0] for i in range(FRAMES) for line in (out / f"label_2/{i:06d}.txt").read_text().splitlines()]
    preview = make_preview(out, tmp_path / "sheet.png")
    assert preview.summary.objects_per_class == {name: lines.count(name) for name in dict.fromkeys(lines)}


@settings(max_examples=300, deadline=None)
@given(left=st.integers(0, 4000), top=st.integers(0, 3000), w=st.integers(0, 100), h=st.integers(0, 100),
       visible=st.integers(1, 10**6), extra=st.integers(0, 10**6))
def test_a_dontcare_line_is_its_box_and_kittis_placeholders_and_the_defaults_label_every_target(left, top, w, h,
                                                                                                visible, extra):
    from seasynth.worker.frame.labels import Box2D, dont_care, labelled

    line = kitti.format_label_line(dont_care(Box2D(left, top, left + w, top + h, visible)))
    assert line == (f"DontCare -1.00 -1 -10.00 {left}.00 {top}.00 {left + w}.00 {top + h}.00 -1.00 -1.00 -1.00 "
                    "-1000.00 -1000.00 -1000.00 -10.00")
    assert labelled(visible, visible + extra, 1, 0.0)  # the defaults keep every target with a visible pixel
    assert labelled(visible, visible + extra, visible, 0.0) and not labelled(visible, visible + extra, visible + 1, 0)
    assert labelled(visible, visible, 1, 1.0)  # a target wholly visible passes any fraction
    assert labelled(visible, visible + extra, 1, 0.5) == (2 * visible >= visible + extra)
