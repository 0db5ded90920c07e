"""A frame's exported objects: its label_2 lines as objects, given their instance ids, pixel counts and classes
from the instance masks and meta, and the visible distractors."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.spec.targets import DONT_CARE
from seasynth.worker.frame.kitti import parse_label_file
from seasynth.worker.frame.labels import tight_box_arrays


@dataclass(frozen=True)
class FrameObject:
    """One exported object. box: (left, top, right, bottom), inclusive 0-based pixel indices (KITTI's label_2
    box, whose pixel i covers [i - 0.5, i + 0.5] in KITTI's centre convention)."""

    category: int | None  # index of its class in spec.class_names, or len(class_names) for a distractor; None for
    # an ignored region (a DontCare line) until masks are read (its meta record names its class)
    box: tuple[int, int, int, int]
    instance_id: int | None  # the id in the instance image; None when masks were not read
    pixels: int | None  # visible pixels (the instance id's pixel count); None when masks were not read
    truncated: float | None  # KITTI's, from the label line; None for distractors (no label line)
    occluded: int | None  # KITTI's 0..2; None for distractors
    label_line: int | None  # 0-based line in label_2; None for distractors
    ignore: bool = False  # a DontCare line: a target below the label filters (spec labels), a region to ignore



def label_objects(path: Path, text: str, class_names: tuple[str, ...]) -> list[FrameObject]:
    """The label_2 lines as objects (no masks yet); boxes must be whole pixel indices, each line's type one of the
    spec's classes or DontCare."""

    try:
        parsed = parse_label_file(text)
    except ValueError as err:
        raise ExportError(f"{path}: {err}") from None
    objects = []
    index = {name: k for k, name in enumerate(class_names)}
    for k, lab in enumerate(parsed):
        if lab["type"] not in index and lab["type"] != DONT_CARE:
            raise ExportError(f"{path}: line {k + 1} has type {lab['type']!r}, not one of the spec's classes "
                              f"({', '.join(map(repr, class_names))}) nor {DONT_CARE}")
        box = tuple(int(round(v)) for v in lab["bbox"])
        if any(b != v for b, v in zip(box, lab["bbox"])) or not (box[0] <= box[2] and box[1] <= box[3]):
            raise ExportError(f"{path}: line {k + 1} box {lab['bbox']} is not an inclusive box of whole pixels")
        ignore = lab["type"] == DONT_CARE
        objects.append(FrameObject(category=index.get(lab["type"]), box=box, instance_id=None, pixels=None,
                                   truncated=None if ignore else lab["truncated"],
                                   occluded=None if ignore else lab["occluded"], label_line=k, ignore=ignore))
    return objects


def with_masks(objects: list[FrameObject], instance: np.ndarray, meta: dict, where: str, label_path: Path,
                distractors: bool, class_names: tuple[str, ...]) -> list[FrameObject]:
    """Give each label line its instance id (meta's objects[].label_line) and pixel count, checking that the
    tight box of that id's pixels is the line's box, and each DontCare line its class (meta's objects[].class);
    then add the visible distractors when asked."""

    ids, boxes, counts = tight_box_arrays(instance)
    present = {int(i): (tuple(int(v) for v in b), int(c)) for i, b, c in zip(ids, boxes, counts)}
    try:
        records = [(int(o["instance_id"]), o["role"], o["label_line"]) for o in meta["objects"]]
        class_of = {int(o["instance_id"]): o.get("class") for o in meta["objects"]}
    except (KeyError, TypeError, ValueError) as err:
        raise ExportError(f"meta/{label_path.stem}.json of {where}: objects lack instance_id, role or "
                          f"label_line ({err})") from None
    id_of_line = {line: iid for iid, _, line in records if line is not None}
    if sorted(id_of_line) != list(range(len(objects))):
        raise ExportError(f"{label_path}: {len(objects)} lines, but meta's objects name label lines "
                          f"{sorted(id_of_line)}")
    out = []
    for obj in objects:
        iid = id_of_line[obj.label_line]
        box, pixels = present.get(iid, (None, 0))
        if box != obj.box:
            raise ExportError(f"{label_path}: line {obj.label_line + 1} box {obj.box} is not the tight box "
                              f"{box} of instance id {iid} in {where}")
        category = obj.category
        if obj.ignore:
            if class_of[iid] not in class_names:
                raise ExportError(f"{label_path}: line {obj.label_line + 1} (DontCare) is instance id {iid}, whose "
                                  f"class {class_of[iid]!r} in meta is not one of the spec's")
            category = class_names.index(class_of[iid])
        out.append(FrameObject(category=category, box=obj.box, instance_id=iid, pixels=pixels,
                               truncated=obj.truncated, occluded=obj.occluded, label_line=obj.label_line,
                               ignore=obj.ignore))
    if distractors:
        for iid, role, _ in sorted(records):
            if role == "distractor" and iid in present:
                box, pixels = present[iid]
                out.append(FrameObject(category=len(class_names), box=box, instance_id=iid, pixels=pixels,
                                       truncated=None, occluded=None, label_line=None))
    return out
