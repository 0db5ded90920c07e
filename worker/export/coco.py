"""COCO detection export: images/{split}/*.png and annotations/instances_{split}.json, streamed to disk.

Per split, the `images` and `annotations` arrays are appended to two temporary files as frames arrive (one JSON
object per line), and `finish` assembles the final file by copying them between the fixed head and tail, so memory
stays flat in the number of frames.

- image: `id` = frame index, `file_name` = "000123.png" (or .jpg; under images/{split}/), `width`, `height` (px),
  and `camera_model` where the spec has a port or a lens distortion: K, Brown-Conrady `distortion` [k1, k2, p1, p2,
  k3] and `port` (seasynth.service.camera_model.CameraModel.from_record maps its pixels to rays in water).
- annotation: `id` = frame index * 65536 + instance id (unique, >= 1, the same whatever the split), `image_id`,
  `category_id` (i + 1 for the spec's i-th target class, then "distractor" with --distractors), `bbox`
  (coco_bbox), `area` = the instance's pixel count, `iscrowd` = 0, or 1 for a region to ignore (a DontCare line:
  a target below the spec's label filters), `segmentation` = compressed COCO RLE of the instance id's pixels in
  instance/ (or re-rendered ones), and KITTI's `truncated`, `occluded` (null for distractors and regions to
  ignore) and 0-based `kitti_line` (null for distractors, which have no label line), and the `instance_id`.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import BinaryIO

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.spec.outputs import SPLITS
from seasynth.worker.export.base import ExportInfo
from seasynth.worker.export.dataset import Frame
from seasynth.worker.export.files import atomic_writer, make_dirs, place_file, tmp_name

ANN_ID_STRIDE = 1 << 16  # instance ids are uint16, so frame * stride + id never collides
STREAMS = ("images", "annotations")


def coco_bbox(box: tuple[int, int, int, int]) -> list[int]:
    """COCO [x, y, w, h] (px, pixel-edge coordinates: pixel (u, v) covers [u, u + 1] x [v, v + 1]) of a KITTI box
    (left, top, right, bottom) of inclusive 0-based pixel indices: x = left, y = top, w = right - left + 1,
    h = bottom - top + 1. Exact integers; it is pycocotools.mask.toBbox of the box's pixels."""
    left, top, right, bottom = box
    return [left, top, right - left + 1, bottom - top + 1]


def instance_runs(instance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of equal ids along COCO's pixel order (column-major: down each column, columns left to right).

    instance: (h, w) integer ids. Returns values (k,), starts (k,) int64 and lengths (k,) int64 (pixels), with
    consecutive runs of different values and lengths summing to h * w.
    """
    flat = np.asarray(instance).T.ravel()
    starts = np.r_[0, np.flatnonzero(flat[1:] != flat[:-1]) + 1].astype(np.int64)
    lengths = np.diff(np.r_[starts, flat.size]).astype(np.int64)
    return flat[starts], starts, lengths


def rle_counts(runs: tuple[np.ndarray, np.ndarray, np.ndarray], instance_id: int, size: int) -> np.ndarray:
    """COCO's uncompressed RLE counts (k,) int64 of the pixels equal to `instance_id`: alternating runs of 0s and
    1s in column-major order, starting with 0s (a first count of 0 if pixel (0, 0) is in), as pycocotools'
    rleEncode counts them (no trailing empty run). size = h * w; the id must have at least one pixel."""
    values, starts, lengths = runs
    sel = values == instance_id
    s, n = starts[sel], lengths[sel]
    if s.size == 0:
        raise ValueError(f"instance id {instance_id} has no pixels")
    ends = s + n
    counts = np.empty(2 * s.size, dtype=np.int64)
    counts[0::2] = s - np.r_[0, ends[:-1]]
    counts[1::2] = n
    tail = size - int(ends[-1])
    return np.r_[counts, tail] if tail else counts


def rle_string(counts: np.ndarray) -> str:
    """COCO's compressed RLE text of uncompressed counts (pycocotools' rleToString): each count, less the count
    two before it from the third on, in 5-bit groups with a continuation bit, offset by 48 to printable ASCII."""
    out = bytearray()
    values = [int(c) for c in counts]
    for i, x in enumerate(values):
        if i > 2:
            x -= values[i - 2]
        while True:
            c = x & 0x1F
            x >>= 5  # arithmetic shift, as C's on a signed long
            more = x != -1 if c & 0x10 else x != 0
            out.append((c | 0x20 if more else c) + 48)
            if not more:
                break
    return out.decode("ascii")


def _line(entry: dict) -> bytes:
    return json.dumps(entry, sort_keys=True, separators=(",", ":")).encode()


def coco_head(info: ExportInfo, split: str) -> dict:
    """What instances_{split}.json holds besides its images and annotations."""
    return {
        "info": {"description": f"seasynth dataset, {split} split", "version": info.code_version,
                 "dataset_seed": info.dataset_seed, "spec_sha256": info.spec_sha256,
                 "split": split, "split_fractions": dict(zip(SPLITS, info.fractions))},
        "licenses": [],
        "categories": [{"id": k + 1, "name": name,
                        "supercategory": "distractor" if info.distractors and k == len(info.categories) - 1
                        else "target"} for k, name in enumerate(info.categories)],
    }


class CocoExporter:
    """COCO "instances" files, one per split (every split has one, with no images if none fell in it)."""

    needs_masks = True
    folder_globs = ("annotations/instances_*.json",)

    def __init__(self) -> None:
        self._info: ExportInfo | None = None
        self._files: dict[tuple[str, str], BinaryIO] = {}
        self._written: dict[tuple[str, str], int] = {}

    def frame_outputs(self, split: str, name: str) -> tuple[str, ...]:
        return (f"images/{split}/{name}{self._info.image_suffix}",)

    def folder_outputs(self) -> tuple[str, ...]:
        return tuple(f"annotations/instances_{split}.json" for split in SPLITS)

    def index_path(self, split: str) -> Path:
        return self._info.out / "annotations" / f"instances_{split}.json"

    def _stream_path(self, split: str, stream: str) -> Path:
        return tmp_name(self.index_path(split).with_name(f"instances_{split}.json.{stream}"))

    def begin(self, info: ExportInfo) -> None:
        self._info = info
        make_dirs(info.out / "annotations", *(info.out / "images" / split for split in SPLITS))
        for split in SPLITS:
            for stream in STREAMS:
                path = self._stream_path(split, stream)
                try:
                    self._files[split, stream] = open(path, "wb")
                except OSError as err:
                    self.abort()
                    raise ExportError(f"{path}: cannot write ({err.strerror or err})") from None
                self._written[split, stream] = 0

    def _append(self, split: str, stream: str, entry: dict) -> None:
        f = self._files[split, stream]
        f.write((b",\n" if self._written[split, stream] else b"\n") + _line(entry))
        self._written[split, stream] += 1

    def add_entries(self, split: str, images: list[dict], annotations: list[dict]) -> None:
        """Entries made by another export of the same dataset (a shard's part), after those added so far."""
        for stream, entries in (("images", images), ("annotations", annotations)):
            for entry in entries:
                self._append(split, stream, entry)

    def add(self, frame: Frame, split: str) -> None:
        info = self._info
        place_file(frame.image, info.out / self.frame_outputs(split, frame.name)[0])
        image = {"id": frame.index, "file_name": f"{frame.name}{info.image_suffix}", "width": frame.width,
                 "height": frame.height}
        if info.camera is not None:
            image["camera_model"] = info.camera
        self._append(split, "images", image)
        runs = instance_runs(frame.instance)
        size = frame.width * frame.height
        for obj in frame.objects:
            counts = rle_counts(runs, obj.instance_id, size)
            self._append(split, "annotations", {
                "id": frame.index * ANN_ID_STRIDE + obj.instance_id,
                "image_id": frame.index,
                "category_id": obj.category + 1,
                "bbox": coco_bbox(obj.box),
                "area": obj.pixels,
                "iscrowd": int(obj.ignore),
                "segmentation": {"size": [frame.height, frame.width], "counts": rle_string(counts)},
                "instance_id": obj.instance_id,
                "truncated": obj.truncated,
                "occluded": obj.occluded,
                "kitti_line": obj.label_line,
            })

    def finish(self) -> None:
        for split in SPLITS:
            for stream in STREAMS:
                self._files[split, stream].close()
            head = coco_head(self._info, split)
            with atomic_writer(self.index_path(split)) as out:
                out.write(_line(head)[:-1])  # the object stays open for the two arrays
                for stream in STREAMS:
                    out.write(f',"{stream}":['.encode())
                    with open(self._stream_path(split, stream), "rb") as f:
                        shutil.copyfileobj(f, out)
                    out.write(b"\n]" if self._written[split, stream] else b"]")
                out.write(b"}\n")
        self.abort()  # the streams are copied: remove them

    def abort(self) -> None:
        for f in self._files.values():
            f.close()
        if self._info is not None:
            for split in SPLITS:
                for stream in STREAMS:
                    self._stream_path(split, stream).unlink(missing_ok=True)
        self._files.clear()
