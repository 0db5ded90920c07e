"""`seasynth fetch --format`: the shards' export parts (seasynth.worker.export.parts) merged into one export folder.

COCO and YOLO come out as `seasynth export` of the fetched KITTI dataset writes them, file for file and byte for
byte, but for the record seasynth-export.json (which says where the export came from): COCO's instances_{split}.json
holds every part's images and annotations in shard order, written by the same CocoExporter, and its annotation ids
(frame index * 65536 + instance id) are unique across shards; YOLO's data.yaml names this folder. MCAP keeps one
bag per shard and split: {split}-{shard index:06d}.mcap, side by side in the folder.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from seasynth.service.errors import ExportError, SpecError
from seasynth.service.shards import frame_name
from seasynth.service.spec.dataset import DatasetSpec, parse_spec, spec_digest
from seasynth.worker.export import SPLITS, STREAM_SPLIT, ExportInfo, exporter_for
from seasynth.worker.export.coco import coco_head
from seasynth.worker.export.files import (
    EXPORT_RECORD,
    json_bytes,
    make_dirs,
    open_export_folder,
    place_file,
    write_atomic,
)
from seasynth.worker.export.parts import part_info


class PartMerger:
    """seasynth.service.fetch.ExportMerger of one format."""

    def __init__(self, fmt: str) -> None:
        if fmt not in MERGES:
            raise ExportError(f"format {fmt!r} is not one of {', '.join(MERGES)}")
        self.format = fmt

    def prepare(self, out: Path) -> None:
        open_export_folder(Path(out), self.format)

    def merge(self, manifest: dict[str, Any], parts: list[tuple[dict[str, Any], Path]], out: Path) -> int:
        """Merge (shard entry, folder of its extracted part) in shard order into `out`; the files written."""
        out = Path(out).absolute()
        spec = _spec(manifest)
        info = part_info(spec, out, manifest.get("code_version"))
        parts = sorted(parts, key=lambda p: p[0]["index"])
        written, counts = MERGES[self.format](info, parts)
        _remove_unwritten(out, written)
        write_atomic(out / EXPORT_RECORD, json_bytes(_record(self.format, manifest, spec, info, counts, len(parts))))
        return len(written) + 1


def _spec(manifest: dict[str, Any]) -> DatasetSpec:
    try:
        return parse_spec(manifest["spec"], source=f"manifest of dataset {manifest.get('id')}: spec")
    except SpecError as err:
        raise ExportError(str(err)) from None


def _merge_coco(info: ExportInfo, parts: list[tuple[dict, Path]]) -> tuple[set[str], dict[str, int]]:
    """Every part's images, and its annotations appended after the parts before it, through one CocoExporter."""
    exporter = exporter_for("coco")
    exporter.begin(info)
    written, counts = set(), dict.fromkeys(SPLITS, 0)
    try:
        for shard, folder in parts:
            for split in SPLITS:
                path = folder / "annotations" / f"instances_{split}.json"
                data = _read_json(path)
                head = {k: v for k, v in data.items() if k not in ("images", "annotations")}
                if head != coco_head(info, split):
                    raise ExportError(f"{path}: shard {shard['index']}'s part was made for another dataset, spec, "
                                      "code version or split than its manifest says")
                for image in data["images"]:
                    rel = f"images/{split}/{_plain_name(image.get('file_name'), path)}"
                    place_file(_existing(folder / rel), info.out / rel)
                    written.add(rel)
                exporter.add_entries(split, data["images"], data["annotations"])
                counts[split] += len(data["images"])
        exporter.finish()
    except BaseException:
        exporter.abort()
        raise
    return written | {f"annotations/instances_{split}.json" for split in SPLITS}, counts


def _merge_yolo(info: ExportInfo, parts: list[tuple[dict, Path]]) -> tuple[set[str], dict[str, int]]:
    """Every part's images/ and labels/ files, then data.yaml naming this folder. A part must hold one image and
    one label file for each frame of its shard, or the merge stops naming it (a part folder removed or emptied
    since it was fetched)."""
    exporter = exporter_for("yolo")
    exporter.begin(info)
    written, counts = set(), dict.fromkeys(SPLITS, 0)
    for shard, folder in parts:
        files = {(kind, split): sorted(p for p in (folder / kind / split).glob("*") if p.is_file())
                 for kind in ("images", "labels") for split in SPLITS}
        images = sorted(p.stem for split in SPLITS for p in files["images", split])
        labels = sorted(p.stem for split in SPLITS for p in files["labels", split])
        first = shard["first_frame"]
        want = [frame_name(i) for i in range(first, first + shard["frame_count"])]
        if images != want or labels != want:
            raise ExportError(f"{folder}: shard {shard['index']}'s YOLO part holds {len(images)} images and "
                              f"{len(labels)} label files for its {shard['frame_count']} frames (remove the "
                              "folder's .seasynth-fetch/ and fetch again)")
        for (kind, split), srcs in files.items():
            for src in srcs:
                rel = f"{kind}/{split}/{src.name}"
                place_file(src, info.out / rel)
                written.add(rel)
                counts[split] += kind == "images"
    exporter.finish()
    return written | {"data.yaml"}, counts


def _merge_mcap(info: ExportInfo, parts: list[tuple[dict, Path]]) -> tuple[set[str], dict[str, int]]:
    """Each part's bags, renamed {split}-{shard index:06d}.mcap (frame counts are not read back from the bags)."""
    make_dirs(info.out)
    written = set()
    for shard, folder in parts:
        for split in SPLITS:
            rel = mcap_name(split, shard["index"])
            place_file(_existing(folder / f"{split}.mcap"), info.out / rel)
            written.add(rel)
    return written, {}


def mcap_name(split: str, shard_index: int) -> str:
    """A fetched MCAP export's bag of one shard's frames in `split`."""
    return f"{split}-{shard_index:06d}.mcap"


MERGES = {"coco": _merge_coco, "yolo": _merge_yolo, "mcap": _merge_mcap}


def _record(fmt: str, manifest: dict, spec: DatasetSpec, info: ExportInfo, counts: dict[str, int],
            parts: int) -> dict:
    """seasynth-export.json: run_export's fields, the dataset named by its manifest."""
    frames = sum(s["frame_count"] for s in manifest["shards"])
    return {
        "format": fmt,
        "state": "complete",
        "split": dict(zip(SPLITS, info.fractions)),
        "split_rule": "SeedSequence([dataset seed, frame index, STREAM_SPLIT]) uniform vs cumulative fractions",
        "split_stream": STREAM_SPLIT,
        "frames": counts or None,  # MCAP's are in each bag's metadata
        "frames_skipped": spec.frames - frames,
        "categories": list(info.categories),
        "masks": "rendered at generate time" if fmt == "coco" else None,
        "dataset": {"id": manifest.get("id"), "seed": spec.seed, "spec_sha256": spec_digest(spec),
                    "code_version": manifest.get("code_version"), "renderer": manifest.get("renderer"),
                    "record": "manifest (seasynth fetch --format)"},
        "parts": parts,
    }


def _remove_unwritten(out: Path, written: set[str]) -> None:
    """Delete files under `out` this merge did not write (an earlier fetch's), except the record and the fetch's
    own hidden state: the folder then holds exactly this export."""
    try:
        for dirpath, dirnames, filenames in os.walk(out):
            dirnames[:] = [d for d in dirnames if not d.startswith(".")]
            for name in filenames:
                rel = Path(dirpath, name).relative_to(out).as_posix()
                if rel != EXPORT_RECORD and rel not in written:
                    os.unlink(Path(dirpath, name))
    except OSError as err:
        raise ExportError(f"{out}: cannot remove files of an earlier export ({err.strerror or err})") from None


def _plain_name(name, where: Path) -> str:
    """A COCO image's file_name, if it is a plain file name (it is joined to paths inside and outside the part)."""
    if not isinstance(name, str) or not name or "/" in name or "\\" in name or name in (".", ".."):
        raise ExportError(f"{where}: image file_name {name!r} is not a plain file name")
    return name


def _existing(path: Path) -> Path:
    if not path.is_file():
        raise ExportError(f"{path}: missing from its fetched part (remove the folder's .seasynth-fetch/ and fetch "
                          "again)")
    return path


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(_existing(path).read_text())
    except (OSError, ValueError) as err:
        raise ExportError(f"{path}: unreadable ({err})") from None
    if not isinstance(data, dict) or not isinstance(data.get("images"), list) \
            or not isinstance(data.get("annotations"), list):
        raise ExportError(f"{path}: not a COCO instances file")
    return data
