"""Export parts: one shard's frames in a detector format (spec outputs.coco, yolo, mcap), written at generate time.

A part is what `seasynth export` writes for those frames alone, less the files that name the export folder
(YOLO's data.yaml, rebuilt by seasynth.worker.export.merge): COCO's images/{split}/*.png and annotations/instances_{split}
.json of the shard's frames, YOLO's images/ and labels/, MCAP's {split}.mcap. Every frame gets the split
split_of(seed, index, outputs.split) gives it, whatever the shard, so merged parts equal one export of the whole
dataset. A part is a pure function of (spec, code version, the shard's frame files).
"""

from __future__ import annotations

import json
from pathlib import Path

from seasynth.service.errors import ExportError
from seasynth.service.shards import frame_file
from seasynth.service.spec.dataset import DatasetSpec, spec_digest
from seasynth.worker.export import SPLITS, ExportInfo, exporter_class, exporter_for, split_of
from seasynth.worker.export.base import camera_record
from seasynth.worker.export.dataset import decode_instance, frame_of, mask_spec

# Files of an export that describe the folder rather than frames: left out of parts, written by the merge.
REBUILT_AT_MERGE = {"yolo": ("data.yaml",)}


def needs_masks(spec: DatasetSpec) -> bool:
    """Whether one of the spec's export formats needs instance masks (COCO's segmentations)."""
    return any(exporter_class(fmt).needs_masks for fmt in spec.outputs.exports)


def parts_render_spec(spec: DatasetSpec) -> DatasetSpec:
    """What a shard with export parts renders: `spec`, or with instance/ and meta/ on when a format needs masks
    (the frames' image_2, label_2 and calib bytes are the same either way: seasynth.worker.export.dataset.mask_spec)."""
    return mask_spec(spec) if needs_masks(spec) else spec


def kitti_names(spec: DatasetSpec, render: DatasetSpec, index: int, names: list[str]) -> list[str]:
    """Of the files frame `index` rendered with `render` has, those `spec` asks for, sorted."""
    o, r = spec.outputs, render.outputs
    extra = set()
    if r.instance and not o.instance:
        extra.add(frame_file("instance", index))
    if r.meta and not o.meta:
        extra.add(frame_file("meta", index))
    return sorted(name for name in names if name not in extra)


def part_info(spec: DatasetSpec, out: Path, code_version: str | None) -> ExportInfo:
    """The ExportInfo `seasynth export` uses for a dataset of `spec` (no --distractors, outputs.split)."""
    return ExportInfo(out=Path(out).absolute(), categories=spec.class_names, width=spec.camera.width,
                      height=spec.camera.height, dataset_seed=spec.seed, spec_sha256=spec_digest(spec),
                      code_version=code_version, fractions=spec.outputs.split, sensors=spec.sensors,
                      image_format=spec.outputs.image_format, trajectory=spec.trajectory,
                      camera=camera_record(spec.camera))


def write_part(spec: DatasetSpec, fmt: str, frames: range, root: Path, out: Path,
               code_version: str | None) -> list[str]:
    """Write format `fmt`'s files for `frames` into the empty folder `out`; return the part's members (relative
    paths, sorted).

    root holds the frames' files as parts_render_spec(spec) renders them (KITTI layout): masks come from its
    instance/ and meta/ when the format needs them, whether or not `spec` keeps those outputs.
    """
    exporter = exporter_for(fmt)
    exporter.begin(part_info(spec, out, code_version))
    try:
        for index in frames:
            label = _read(root / frame_file("label", index))
            masks = None
            if exporter.needs_masks:
                rel_instance = frame_file("instance", index)
                masks = (decode_instance(_read(root / rel_instance), f"rendered {rel_instance}"),
                         json.loads(_read(root / frame_file("meta", index))), f"rendered {rel_instance}")
            split = SPLITS[split_of(spec.seed, index, spec.outputs.split)]
            exporter.add(frame_of(spec, root, index, label, masks, distractors=False), split)
        exporter.finish()
    except BaseException:
        exporter.abort()
        raise
    skip = set(REBUILT_AT_MERGE.get(fmt, ()))
    return sorted(rel for p in Path(out).rglob("*")
                  if p.is_file() and (rel := p.relative_to(out).as_posix()) not in skip)


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise ExportError(f"{path}: unreadable ({err.strerror or err})") from None
