"""`seasynth preview`: a contact sheet of a dataset's first frames (boxes, depth, instances, the FLS fan with its
boxes) and a label summary.

The drawing is seasynth.service.sheet's (the API draws the same sheet of a service dataset); this module reads a local one.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.files import atomic_path
from seasynth.service.shards import frame_file
from seasynth.service.sheet import (
    TILE_WIDTH,
    Summary,
    SummaryCounter,
    Tile,
    class_colour,
    decode_png,
    draw_sheet,
    jerlov_of,
    markdown,
    tile_size,
)
from seasynth.service.spec.targets import DONT_CARE
from seasynth.worker.export.dataset import FrameReader, open_local_dataset, scan_frames


@dataclass(frozen=True)
class Preview:
    summary: Summary
    sheet: Path
    table: Path
    tiles: int


def _read_png(path: Path) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ExportError(f"{path}: cannot decode ({err.strerror or err})") from None
    return decode_png(data, str(path))


def _jerlov(path: Path | None) -> str | None:
    if path is None:
        return None
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ExportError(f"{path}: unreadable meta ({err})") from None
    return jerlov_of(meta)


def _fls_fan(files: dict[str, Path], colours: dict) -> tuple[np.ndarray | None, tuple]:
    """The frame's FLS fan image ((h, w) uint16) and its targets' fan boxes (class, box, colour), or (None, ())
    for a dataset without the FLS."""
    if "fls_fan" not in files:
        return None, ()
    try:
        objects = json.loads(files["fls_label"].read_text())["objects"]
        boxes = tuple((o["class"], (o["fan_box"]["left"], o["fan_box"]["top"], o["fan_box"]["right"],
                                    o["fan_box"]["bottom"]), class_colour(colours, o["class"])) for o in objects)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ExportError(f"{files['fls_label']}: unreadable FLS labels ({err!r})") from None
    return _read_png(files["fls_fan"]), boxes


def make_preview(dataset: Path, out: Path, frames: int = 12,
                 on_frames: Callable[[int], None] | None = None,
                 on_total: Callable[[int], None] | None = None,
                 tile_width: int | None = None) -> Preview:
    """Write the contact sheet of the first `frames` complete frames to `out` (.png) and the summary over all
    complete frames to `out` with suffix .md, each atomically. Frames wider than `tile_width` px (None:
    TILE_WIDTH) are drawn scaled down. on_total gets the complete frame count once it is known, on_frames the
    frames read since its last call."""
    if frames < 1:
        raise ExportError(f"--frames must be at least 1, got {frames}")
    tile_width = TILE_WIDTH if tile_width is None else tile_width
    tile_size(1, 1, tile_width)  # refuses a width below 1 before any work
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ExportError(f"{out}: the sheet is a PNG; give a name ending in .png")
    if not out.parent.is_dir():
        raise ExportError(f"{out.parent}: no such folder for the sheet")
    ds = open_local_dataset(dataset)
    indices = np.flatnonzero(scan_frames(ds).complete)
    if len(indices) == 0:
        raise ExportError(f"{ds.root}: no complete frame to preview")
    if on_total is not None:
        on_total(len(indices))
    o = ds.spec.outputs
    counter, tiles, colours = SummaryCounter(), [], {}
    with FrameReader(ds, masks=False, distractors=False) as reader:
        for index in indices:
            frame = reader.read(int(index))
            named = [(DONT_CARE if ob.ignore else ds.spec.class_names[ob.category], ob) for ob in frame.objects]
            counter.add(((name, ob.box, ob.truncated, ob.occluded) for name, ob in named), _jerlov(frame.meta))
            boxes = tuple((name, ob.box, class_colour(colours, name)) for name, ob in named)
            if len(tiles) < frames:
                fan, fan_boxes = _fls_fan(frame.sensor_files, colours)
                tiles.append(Tile(
                    name=frame.name, image=_read_png(frame.image)[..., :3].astype(np.uint8), boxes=boxes,
                    depth=None if frame.depth is None else _read_png(frame.depth),
                    instance=_read_png(ds.root / frame_file("instance", int(index))) if o.instance else None,
                    sonar=fan, sonar_boxes=fan_boxes,
                ))
            if on_frames is not None:
                on_frames(1)
    summary = counter.result()
    sheet = draw_sheet(tiles, summary, tile_width)
    table = out.with_suffix(".md")
    _write_atomic(out, lambda p: sheet.save(p, format="PNG"))
    _write_atomic(table, lambda p: p.write_text(markdown(summary)))
    return Preview(summary=summary, sheet=out, table=table, tiles=len(tiles))


def _write_atomic(path: Path, write: Callable[[Path], None]) -> None:
    """write(temporary path), then rename onto `path`: readers never see half a file."""
    with atomic_path(path, ExportError) as tmp:
        write(tmp)