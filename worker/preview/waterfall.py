"""`seasynth waterfall`: a local dataset's side-scan rows (sss/) stacked in frame order into one waterfall image,
with the targets' boxes from sss_label/.

Row i of the waterfall is frame i's ping (port far..near, then starboard near..far; nadir in the middle), drawn
`row_height` px high. Rows are stacked as they are: the turns between survey legs are not marked. A box is one run
of consecutive frames in which a target (instance id) is labelled on one side: rows = the run, columns = the union
of the run's column spans.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.sheet import BOX_COLOURS, decode_png, draw_boxes, sonar_grey
from seasynth.worker.export.dataset import open_local_dataset
from seasynth.worker.preview.sheet import _write_atomic

Box = tuple[int, int, int, int]  # (left, top, right, bottom), inclusive: columns and frame rows


@dataclass(frozen=True)
class Waterfall:
    rows: np.ndarray  # (frames, 2 * range_bins) uint16: the sss/ rows in frame order
    boxes: tuple[tuple[str, int, str, Box], ...]  # (class, instance id, side, box in rows and columns)


def waterfall_boxes(labels: list[list[dict]]) -> list[tuple[str, int, str, Box]]:
    """Boxes of per-frame sss_label objects (frame order): one per run of consecutive frames in which an instance is
    labelled on a side, sorted by (top, side, instance id)."""
    runs: dict[tuple[int, str], list] = {}  # (instance, side) -> the open run [class, first, last, left, right]
    out = []
    for i, objects in enumerate(labels):
        for o in objects:
            key = (o["instance_id"], o["side"])
            run = runs.get(key)
            if run is not None and run[2] == i - 1:
                run[2], run[3], run[4] = i, min(run[3], o["column_min"]), max(run[4], o["column_max"])
            else:
                if run is not None:
                    out.append((run[0], key[0], key[1], (run[3], run[1], run[4], run[2])))
                runs[key] = [o["class"], i, i, o["column_min"], o["column_max"]]
    out += [(run[0], key[0], key[1], (run[3], run[1], run[4], run[2])) for key, run in runs.items()]
    return sorted(out, key=lambda b: (b[3][1], b[2], b[1]))


def read_waterfall(dataset: Path) -> Waterfall:
    """Every frame's sss/ row and sss_label/ objects of a local dataset (generate or fetch); ExportError naming
    the file for a missing or malformed one."""
    ds = open_local_dataset(dataset)
    sss = ds.spec.sensors.sss
    if not sss.enabled:
        raise ExportError(f"{ds.root}: the dataset has no side-scan sonar (sensors.sss.enabled is false)")
    rows, labels = [], []
    for i in range(ds.spec.frames):
        row_path, label_path = ds.root / f"sss/{i:06d}.png", ds.root / f"sss_label/{i:06d}.json"
        if not row_path.is_file():
            raise ExportError(f"{row_path}: missing (the waterfall needs every frame; complete the dataset first)")
        try:
            row = decode_png(row_path.read_bytes(), str(row_path))
        except OSError as err:
            raise ExportError(f"{row_path}: unreadable ({err.strerror or err})") from None
        if row.shape != (1, 2 * sss.range_bins) or row.dtype != np.uint16:
            raise ExportError(f"{row_path}: {row.shape} {row.dtype}, the spec says (1, {2 * sss.range_bins}) uint16")
        try:
            labels.append(json.loads(label_path.read_text())["objects"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ExportError(f"{label_path}: unreadable side-scan labels ({err!r})") from None
        rows.append(row)
    return Waterfall(rows=np.concatenate(rows, axis=0), boxes=tuple(waterfall_boxes(labels)))


def draw_waterfall(w: Waterfall, row_height: int, labels: bool) -> np.ndarray:
    """(frames * row_height, 2 * range_bins, 3) uint8: the rows in grey (seasynth.service.sheet.sonar_grey over the whole
    waterfall), each repeated row_height times; with labels, each box's 1-px outline in its class's colour, rows
    [top * row_height, (bottom + 1) * row_height - 1], and its class name above it."""
    from PIL import ImageFont

    if row_height < 1:
        raise ExportError(f"--row-height must be at least 1, got {row_height}")
    grey = np.repeat(sonar_grey(w.rows), row_height, axis=0)
    image = np.repeat(grey[..., None], 3, axis=-1)
    if not labels:
        return image
    colours: dict[str, tuple[int, int, int]] = {}
    boxes = [(name, (b[0], b[1] * row_height, b[2], (b[3] + 1) * row_height - 1),
              colours.setdefault(name, BOX_COLOURS[len(colours) % len(BOX_COLOURS)])) for name, _, _, b in w.boxes]
    return draw_boxes(image, boxes, ImageFont.load_default())


def write_waterfall(dataset: Path, out: Path, row_height: int = 1, labels: bool = False) -> tuple[Waterfall, Path]:
    """Write the waterfall of `dataset` to `out` (.png), atomically."""
    from PIL import Image

    out = Path(out)
    if row_height < 1:
        raise ExportError(f"--row-height must be at least 1, got {row_height}")
    if out.suffix.lower() != ".png":
        raise ExportError(f"{out}: the waterfall is a PNG; give a name ending in .png")
    if not out.parent.is_dir():
        raise ExportError(f"{out.parent}: no such folder for the waterfall")
    w = read_waterfall(dataset)
    image = draw_waterfall(w, row_height, labels)
    _write_atomic(out, lambda p: Image.fromarray(image).save(p, format="PNG"))
    return w, out
