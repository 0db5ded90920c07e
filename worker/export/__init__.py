"""Export a local dataset (a `generate` or `fetch` folder) to detector formats: split rule, Exporter protocol, driver.

A format is one module with one Exporter class, registered in FORMATS. The driver reads the dataset's frames one
at a time (seasynth.worker.export.dataset), gives each to the exporter with its split, and owns the export folder's record
and the removal of files an earlier export left that this one does not write. The same exporters write the formats
a spec asks for at generate time: a service shard's part (seasynth.worker.export.parts), merged by `seasynth fetch --format`
(seasynth.worker.export.merge), and a local dataset's OUT/export/{format}/ (export_generated).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.spec.outputs import EXPORT_FORMATS, SPLIT_SUM_TOLERANCE, SPLITS
from seasynth.worker.export.base import STREAM_SPLIT, Exporter, ExportInfo, camera_record, parse_split, split_of
from seasynth.worker.export.dataset import (
    DISTRACTOR_NAME,
    Frame,
    FrameObject,
    FrameReader,
    LocalDataset,
    incompleteness,
    open_local_dataset,
    scan_frames,
)
from seasynth.worker.export.files import EXPORT_RECORD, json_bytes, open_export_folder, write_atomic

__all__ = [
    "DISTRACTOR_NAME", "FORMATS", "GENERATED_EXPORTS", "SPLITS", "SPLIT_SUM_TOLERANCE", "STREAM_SPLIT",
    "ExportInfo", "ExportPlan", "ExportReport", "Exporter", "Frame", "FrameObject", "FrameReader", "LocalDataset",
    "export_generated", "exporter_class", "exporter_for", "open_local_dataset", "parse_split", "plan_export",
    "run_export", "split_of",
]

FORMATS = EXPORT_FORMATS
GENERATED_EXPORTS = "export"  # `seasynth generate` writes the spec's export formats into OUT/export/{format}/


def exporter_class(fmt: str) -> type:
    """The Exporter class of format `fmt` (its module imports no format package: making one may need it)."""
    if fmt == "coco":
        from seasynth.worker.export.coco import CocoExporter

        return CocoExporter
    if fmt == "yolo":
        from seasynth.worker.export.yolo import YoloExporter

        return YoloExporter
    if fmt == "mcap":
        from seasynth.worker.export.mcap import McapExporter

        return McapExporter
    raise ExportError(f"format {fmt!r} is not one of {', '.join(FORMATS)}")


def exporter_for(fmt: str) -> Exporter:
    return exporter_class(fmt)()


@dataclass(frozen=True)
class ExportPlan:
    """What `run_export` will do: the dataset, the format, and each frame's split."""

    dataset: LocalDataset
    format: str
    fractions: tuple[float, float, float]
    distractors: bool
    assignment: np.ndarray  # (frames,) int8: index into SPLITS, -1 for a frame left out (incomplete)
    skipped: int  # incomplete frames left out (only with partial)
    uses_masks: bool  # the format or --distractors needs instance masks
    renders_masks: bool  # ... and the dataset has no instance/ (or meta/): they are re-rendered

    @property
    def frames(self) -> int:
        return int((self.assignment >= 0).sum())

    @property
    def categories(self) -> tuple[str, ...]:
        names = self.dataset.spec.class_names
        return (*names, DISTRACTOR_NAME) if self.distractors else names


@dataclass(frozen=True)
class ExportReport:
    out: Path
    format: str
    frames: dict[str, int]  # split -> frames exported
    skipped: int
    renders_masks: bool


def plan_export(root: Path, fmt: str, fractions: tuple[float, float, float] | None = None, *,
                partial: bool = False, distractors: bool = False) -> ExportPlan:
    """Check the dataset and decide every frame's split (fractions None: its spec's outputs.split); ExportError
    naming what is missing if it is not whole (unless `partial`: then incomplete frames are left out)."""
    if fmt not in FORMATS:
        raise ExportError(f"format {fmt!r} is not one of {', '.join(FORMATS)}")
    ds = open_local_dataset(Path(root))
    if fractions is None:
        fractions = ds.spec.outputs.split
    if distractors and DISTRACTOR_NAME in ds.spec.class_names:
        raise ExportError(f"{ds.root}: a class of targets is named {DISTRACTOR_NAME!r}, the name distractors get "
                          "with --distractors; export without --distractors")
    scan = scan_frames(ds)
    why = incompleteness(ds, scan)
    if why is not None and not partial:
        raise ExportError(f"{why}; pass --partial to export the {scan.frames_complete} complete frames only")
    assignment = np.full(ds.spec.frames, -1, dtype=np.int8)
    for i in range(ds.spec.frames):
        if scan.complete[i]:
            assignment[i] = split_of(ds.spec.seed, i, fractions)
    o = ds.spec.outputs
    needs = exporter_for(fmt).needs_masks or distractors
    return ExportPlan(dataset=ds, format=fmt, fractions=fractions, distractors=distractors, assignment=assignment,
                      skipped=ds.spec.frames - scan.frames_complete, uses_masks=needs,
                      renders_masks=needs and not (o.instance and o.meta))


def run_export(plan: ExportPlan, out: Path, *, on_frames: Callable[[int], None] | None = None,
               platform: str = "egl") -> ExportReport:
    """Write the export into `out` (absent, empty, or an earlier export of the same format, which it replaces).

    Running it twice writes the same bytes. The record seasynth-export.json says "incomplete" until the end.
    """
    out = Path(out).absolute()
    on_frames = on_frames or (lambda n: None)
    exporter = exporter_for(plan.format)
    ds = plan.dataset
    open_export_folder(out, plan.format)
    info = ExportInfo(out=out, categories=plan.categories, distractors=plan.distractors, width=ds.spec.camera.width,
                      height=ds.spec.camera.height, dataset_seed=ds.spec.seed, spec_sha256=ds.spec_sha256,
                      code_version=ds.code_version, fractions=plan.fractions, sensors=ds.spec.sensors,
                      image_format=ds.spec.outputs.image_format, trajectory=ds.spec.trajectory,
                      camera=camera_record(ds.spec.camera))
    counts = dict.fromkeys(SPLITS, 0)
    with FrameReader(ds, masks=exporter.needs_masks, distractors=plan.distractors, platform=platform) as reader:
        exporter.begin(info)
        try:
            for index in range(ds.spec.frames):  # not a list of indices: memory stays flat in the frame count
                k = int(plan.assignment[index])
                if k < 0:
                    continue
                exporter.add(reader.read(index), SPLITS[k])
                counts[SPLITS[k]] += 1
                on_frames(1)
            exporter.finish()
        except BaseException:
            exporter.abort()
            raise
    remove_stale(out, exporter, plan)
    write_atomic(out / EXPORT_RECORD, json_bytes({
        "format": plan.format,
        "state": "complete",
        "split": dict(zip(SPLITS, plan.fractions)),
        "split_rule": "SeedSequence([dataset seed, frame index, STREAM_SPLIT]) uniform vs cumulative fractions",
        "split_stream": STREAM_SPLIT,
        "frames": counts,
        "frames_skipped": plan.skipped,
        "categories": list(plan.categories),
        "masks": "re-rendered" if plan.renders_masks else "instance/" if plan.uses_masks else None,
        "dataset": {"seed": ds.spec.seed, "spec_sha256": ds.spec_sha256, "code_version": ds.code_version,
                    "renderer": ds.renderer, "record": ds.record_file},
    }))
    return ExportReport(out=out, format=plan.format, frames=counts, skipped=plan.skipped,
                        renders_masks=plan.renders_masks)


def export_generated(root: Path, *, on_frames: Callable[[int], None] | None = None,
                     platform: str = "egl") -> list[ExportReport]:
    """The exports a generated dataset's spec asks for (outputs.coco, yolo, mcap), each of every frame into
    root/export/{format}/ with the spec's outputs.split; [] when it asks for none."""
    root = Path(root)
    formats = open_local_dataset(root).spec.outputs.exports
    return [run_export(plan_export(root, fmt), root / GENERATED_EXPORTS / fmt, on_frames=on_frames,
                       platform=platform) for fmt in formats]


def remove_stale(out: Path, exporter: Exporter, plan: ExportPlan) -> None:
    """Delete files in the per-frame folders, and files matching the format's folder_globs, that this export did not
    write (an earlier export's other split, frames now left out, a fetched export's per-shard bags, temporary
    files): the folder then holds exactly this export."""
    keep = set(exporter.folder_outputs())
    for pattern in exporter.folder_globs:
        for path in sorted(out.glob(pattern)):
            if path.is_file() and path.relative_to(out).as_posix() not in keep:
                try:
                    path.unlink()
                except OSError as err:
                    raise ExportError(f"{path}: cannot remove this file of an earlier export "
                                      f"({err.strerror or err})") from None
    frames = plan.dataset.spec.frames
    for k, split in enumerate(SPLITS):
        for folder in sorted({Path(p).parent for p in exporter.frame_outputs(split, "000000")}):
            if not (out / folder).is_dir():
                continue
            try:
                with os.scandir(out / folder) as entries:
                    for entry in entries:
                        if entry.is_dir(follow_symlinks=False):
                            continue  # not something an export writes: left to its owner
                        stem = entry.name.split(".", 1)[0]
                        keep = (len(stem) == 6 and stem.isdigit() and int(stem) < frames
                                and plan.assignment[int(stem)] == k
                                and f"{folder.as_posix()}/{entry.name}" in exporter.frame_outputs(split, stem))
                        if not keep:
                            os.unlink(entry.path)
            except OSError as err:
                raise ExportError(f"{out / folder}: cannot remove files of an earlier export "
                                  f"({err.strerror or err})") from None
