"""The contact sheet of a service dataset (GET /datasets/{id}/preview.png): drawn by seasynth.service.sheet (no GL) from the
tars of its committed shards of lowest index, and cached in the bucket under a key derived from what it was drawn
from (those tars' keys and sha256, the frame count, the tile width and the drawing code's version)."""

from __future__ import annotations

import hashlib
import json
import tarfile
import tempfile
from collections.abc import Iterator
from pathlib import Path

from seasynth.service import __version__
from seasynth.service.errors import ExportError, NotFound, ParameterError
from seasynth.service.kitti import parse_label_file
from seasynth.service.records.store import Records
from seasynth.service.records.types import DatasetRecord, ShardCommit
from seasynth.service.shards import FRAME_PARTS, named_file, preview_key
from seasynth.service.sheet import (
    COLUMNS,
    GAP,
    HEADER,
    TILE_WIDTH,
    SummaryCounter,
    Tile,
    class_colour,
    decode_png,
    draw_sheet,
    jerlov_of,
    png_bytes,
    tile_size,
)
from seasynth.service.spec.dataset import DatasetSpec, parse_spec
from seasynth.service.spec.targets import DONT_CARE
from seasynth.service.storage import ObjectStore

SHEET_FRAMES = 12  # tiles on a sheet by default
MAX_SHEET_FRAMES = 48
# Pixels of a sheet's grid at most (8-bit RGB: 192 MB while drawn): the default sheet of a 1920x1080 dataset with
# depth and instances is about 2.3 Mpx, 48 frames of it at tile_width 768 about 50 Mpx.
MAX_SHEET_PIXELS = 64_000_000
COMMITS_PER_READ = 1000  # shard indices per Redis read while looking for the first committed shards
# The folders of a frame the sheet reads (calib/, clean/ and range/ are skipped unread).
READ = tuple(FRAME_PARTS[part][0] for part in ("image", "label", "meta", "depth", "instance"))


def preview_sources(records: Records, rec: DatasetRecord, frames: int) -> list[ShardCommit]:
    """The committed shards of lowest index that together hold at least `frames` frames (all of them if fewer)."""
    chosen, have = [], 0
    for start in range(0, rec.shards_total, COMMITS_PER_READ):
        if len(chosen) >= rec.shards_done:  # every committed shard is found: none further on
            break
        for commit in records.commits_between(rec.id, start, min(start + COMMITS_PER_READ, rec.shards_total)):
            chosen.append(commit)
            have += commit.frame_count
            if have >= frames:
                return chosen
    return chosen


def preview_digest(sources: list[ShardCommit], frames: int, tile_width: int) -> str:
    """sha256 of what a sheet is drawn from: a new shard of lower index, another size or drawing code, a new key."""
    what = {"code_version": __version__, "frames": frames, "tile_width": tile_width,
            "shards": [[c.key, c.sha256] for c in sources]}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def dataset_preview(store: ObjectStore, records: Records, dataset_id: str, frames: int = SHEET_FRAMES,
                    tile_width: int = TILE_WIDTH) -> tuple[str, bytes]:
    """(cache key, PNG bytes) of the dataset's sheet: `frames` tiles from its first committed shards, over the
    label summary of every frame in those shards. NotFound while no shard is committed (or once purged). The
    sheet is read from the bucket when it was drawn before, else drawn and stored there."""
    if not 1 <= frames <= MAX_SHEET_FRAMES:
        raise ParameterError(f"frames: {frames} is not in 1..{MAX_SHEET_FRAMES}")
    if tile_width < 1:
        raise ParameterError(f"tile_width: {tile_width} px; at least 1")
    rec = records.get(dataset_id)
    if rec.purged:
        raise NotFound(f"dataset {dataset_id} was purged; its objects are gone")
    sources = preview_sources(records, rec, frames)
    if not sources:
        raise NotFound(f"dataset {dataset_id} has no committed shard yet ({rec.state}, 0 of {rec.shards_total}); "
                       "its preview is drawn from the first committed shards: try again once one is")
    key = preview_key(dataset_id, preview_digest(sources, frames, tile_width))
    try:
        return key, store.get_bytes(key)
    except NotFound:
        pass
    spec = parse_spec(rec.spec, source=f"dataset {dataset_id}")
    check_sheet_size(spec, min(frames, rec.frames_total), tile_width)
    png = draw_preview(store, spec, sources, frames, tile_width)
    store.put_bytes(key, png, "image/png")
    # Checked after the write, as workers do: a purge that listed the prefix before it would leave it behind.
    if records.purge_started(dataset_id):
        store.delete(key)
        raise NotFound(f"dataset {dataset_id} was purged; its objects are gone")
    return key, png


def check_sheet_size(spec: DatasetSpec, tiles: int, tile_width: int) -> None:
    """ParameterError where a sheet of `tiles` frames of `spec` at `tile_width` would exceed MAX_SHEET_PIXELS (its
    grid alone: the summary panel below it adds a few hundred rows)."""
    o = spec.outputs
    w, h = tile_size(spec.camera.width, spec.camera.height, tile_width)
    panels = 1 + o.depth + o.instance
    rows = -(-tiles // COLUMNS)
    grid_w, grid_h = GAP + min(tiles, COLUMNS) * (panels * w + GAP), GAP + rows * (HEADER + h + GAP)
    if grid_w * grid_h > MAX_SHEET_PIXELS:
        raise ParameterError(
            f"frames, tile_width: a sheet of {tiles} frames of {spec.camera.width}x{spec.camera.height} ({panels} "
            f"panels each) at tile_width {tile_width} would be {grid_w}x{grid_h} px, over the "
            f"{MAX_SHEET_PIXELS // 10**6} Mpx a sheet may have; ask for fewer frames or a smaller tile_width")


def draw_preview(store: ObjectStore, spec: DatasetSpec, sources: list[ShardCommit], frames: int,
                 tile_width: int) -> bytes:
    """The sheet of the shards `sources` (downloaded one at a time) as PNG bytes."""
    counter, tiles, colours = SummaryCounter(), [], {}
    with tempfile.TemporaryDirectory(prefix="seasynth-preview-") as tmp:
        for commit in sources:
            path = Path(tmp) / "shard.tar"
            store.download(commit.key, path)
            for name, files in frames_of_tar(path, commit.key):
                where = f"{commit.key}: frame {name}"
                objects = _label_lines(files.get(named_file("label", name)), where)
                rel_meta = named_file("meta", name)
                meta = _json(files[rel_meta], where) if rel_meta in files else None
                counter.add(objects, jerlov_of(meta))
                boxes = tuple((cls, box, class_colour(colours, cls)) for cls, box, _, _ in objects)
                if len(tiles) < frames:
                    tiles.append(_tile(spec, name, files, boxes, where))
    return png_bytes(draw_sheet(tiles, counter.result(), tile_width))


def frames_of_tar(path: Path, key: str) -> Iterator[tuple[str, dict[str, bytes]]]:
    """(frame stem, {relative path: bytes} of its READ files) of a shard tar, in its order (frame by frame)."""
    stem, files = None, {}
    try:
        with tarfile.open(path, "r:*") as tar:
            for m in tar:
                folder, _, file = m.name.partition("/")
                this = file.split(".", 1)[0]
                if this != stem:
                    if stem is not None:
                        yield stem, files
                    stem, files = this, {}
                if folder in READ and m.isfile():
                    files[m.name] = tar.extractfile(m).read()
    except (tarfile.TarError, OSError) as err:
        raise ExportError(f"{key}: unreadable shard tar ({err})") from None
    if stem is not None:
        yield stem, files


def _tile(spec: DatasetSpec, name: str, files: dict[str, bytes], boxes: tuple, where: str) -> Tile:
    o = spec.outputs

    def read(part: str):  # image_2 may be a JPEG (outputs.image_format): Pillow decodes either
        rel = named_file(part, name, o.image_suffix)
        data = files.get(rel)
        if data is None:
            raise ExportError(f"{where}: no {rel} in the shard")
        return decode_png(data, f"{where} {FRAME_PARTS[part][0]}")

    return Tile(name=name, image=read("image")[..., :3], boxes=boxes, depth=read("depth") if o.depth else None,
                instance=read("instance") if o.instance else None)


def _label_lines(data: bytes | None, where: str) -> list[tuple[str, tuple[int, int, int, int], float | None,
                                                              int | None]]:
    """(class, box of whole pixels, truncated, occluded) of each label_2 line (truncated and occluded None on a
    DontCare line); none without label_2."""
    if data is None:
        return []
    try:
        lines = parse_label_file(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise ExportError(f"{where}: unreadable label_2 ({err})") from None
    return [(o["type"], tuple(int(round(v)) for v in o["bbox"]), *((None, None) if o["type"] == DONT_CARE else
                                                                   (o["truncated"], o["occluded"]))) for o in lines]


def _json(data: bytes, where: str) -> dict:
    try:
        return json.loads(data)
    except ValueError as err:
        raise ExportError(f"{where}: unreadable meta ({err})") from None
