"""The contact sheet: a dataset's first frames as tiles (image with its boxes, depth, instances) over a label
summary. Pure drawing on decoded arrays (numpy and Pillow, no GL), shared by `seasynth preview` (worker.preview,
a local dataset) and GET /datasets/{id}/preview.png (service.previews, a service dataset's first shards)."""

from __future__ import annotations

import io
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from seasynth.service.errors import ExportError

COLUMNS = 4  # tiles per grid row
GAP = 4  # px between tiles and around the grid
HEADER = 12  # px above each tile for the frame name
LINE = 12  # px per text row of the summary panel
PANEL_MIN_WIDTH = 480  # px: the summary panel's text and bars need this much even under a narrow grid
LABEL_W = 150  # px of a bar row's label column
BAR_MAX = 200  # px of the longest bar
BACKGROUND = (24, 24, 24)
TEXT = (255, 255, 255)
BAR = (90, 160, 230)
BOX_COLOURS = ((255, 0, 255), (0, 255, 0), (255, 255, 0), (0, 255, 255))  # by class, in order of first sight
# Instance ids 1, 2, ... take these in turn (id 0, terrain and water, is black): Kelly's distinct colours.
PALETTE = np.array([
    (255, 179, 0), (128, 62, 117), (255, 104, 0), (166, 189, 215), (193, 0, 32), (206, 162, 98),
    (129, 112, 102), (0, 125, 52), (246, 118, 142), (0, 83, 138), (255, 122, 92), (83, 55, 122),
    (255, 142, 0), (179, 40, 81), (244, 200, 0), (127, 24, 13), (147, 170, 0), (89, 51, 21),
    (241, 58, 19), (35, 44, 22),
], dtype=np.uint8)
HEIGHT_EDGES = tuple(2 ** k for k in range(11))  # box-height bins [1, 2), [2, 4), ... [1024, inf), px
OCCLUDED_LEVELS = (0, 1, 2, 3)  # KITTI: fully visible, partly, largely occluded, unknown
TILE_WIDTH = 320  # px: frames wider than this are scaled down (1920x1080, 3 panels: a sheet 3.9k px wide)


@dataclass(frozen=True)
class Summary:
    """Label statistics over every complete frame of a dataset."""

    frames: int
    objects_per_class: dict[str, int]  # class name -> label lines, in order of first sight
    height_hist: tuple[int, ...]  # objects per HEIGHT_EDGES bin of box height (bottom - top + 1), px
    truncated: int  # objects with KITTI truncated > 0
    occluded: tuple[int, ...]  # objects per OCCLUDED_LEVELS level
    jerlov: dict[str, int] = field(default_factory=dict)  # Jerlov water type -> frames (from meta/), sorted

    @property
    def objects(self) -> int:
        return sum(self.objects_per_class.values())


def height_bin(height: int) -> int:
    """Index into HEIGHT_EDGES of the bin holding a box `height` px high (>= 1)."""
    return int(np.searchsorted(HEIGHT_EDGES, height, side="right")) - 1


def bin_label(k: int) -> str:
    lo = HEIGHT_EDGES[k]
    if k + 1 == len(HEIGHT_EDGES):
        return f">={lo} px"
    hi = HEIGHT_EDGES[k + 1] - 1
    return f"{lo} px" if lo == hi else f"{lo}-{hi} px"


class SummaryCounter:
    """Streamed counts: constant memory whatever the frame count."""

    def __init__(self) -> None:
        self.frames, self.truncated = 0, 0
        self.classes: dict[str, int] = {}
        self.heights = [0] * len(HEIGHT_EDGES)
        self.occluded = [0] * len(OCCLUDED_LEVELS)
        self.jerlov: dict[str, int] = {}

    def add(self, objects: Iterable[tuple[str, tuple[int, int, int, int], float | None, int | None]],
            water: str | None) -> None:
        """One frame: its (class, box, truncated, occluded) label lines and its Jerlov type (None if unknown). A
        DontCare line (truncated and occluded None) counts under its type and box height only."""
        self.frames += 1
        for name, box, truncated, occluded in objects:
            self.classes[name] = self.classes.get(name, 0) + 1
            self.heights[height_bin(box[3] - box[1] + 1)] += 1
            if occluded is not None:
                self.truncated += truncated > 0
                self.occluded[OCCLUDED_LEVELS.index(occluded)] += 1
        if water is not None:
            self.jerlov[water] = self.jerlov.get(water, 0) + 1

    def result(self) -> Summary:
        return Summary(frames=self.frames, objects_per_class=dict(self.classes),
                       height_hist=tuple(self.heights), truncated=self.truncated, occluded=tuple(self.occluded),
                       jerlov=dict(sorted(self.jerlov.items())))


def summary_rows(s: Summary) -> list[tuple[str, str, list[tuple[str, int]]]]:
    """(section title, its text, its bars (label, count)) in the order both the table and the panel show them."""
    n = max(s.objects, 1)
    last = max((k for k, c in enumerate(s.height_hist) if c), default=0)
    return [
        ("frames", f"{s.frames} frames, {s.objects} objects", []),
        ("objects per class", "", list(s.objects_per_class.items())),
        ("box height", "", [(bin_label(k), s.height_hist[k]) for k in range(last + 1)]),
        ("truncated > 0", f"{s.truncated} ({100 * s.truncated / n:.1f}%)", []),
        ("occluded (KITTI level)", "", [(f"level {lv}", c) for lv, c in zip(OCCLUDED_LEVELS, s.occluded)]),
        ("Jerlov water type", "" if s.jerlov else "unknown (no meta/)", list(s.jerlov.items())),
    ]


def markdown(s: Summary) -> str:
    """The summary as a two-column markdown table (percentages of objects, or of frames for water types)."""
    lines = ["| quantity | value |", "| --- | --- |"]
    for title, text, bars in summary_rows(s):
        if text:
            lines.append(f"| {title} | {text} |")
        whole = max(s.frames if title.startswith("Jerlov") else s.objects, 1)
        for label, count in bars:
            lines.append(f"| {title}: {label} | {count} ({100 * count / whole:.1f}%) |")
    return "\n".join(lines) + "\n"


def panel_rows(s: Summary) -> int:
    """Text rows of the summary panel: each section's title line, then one row per bar."""
    return sum(1 + len(bars) for _, _, bars in summary_rows(s))


def sheet_size(tiles: int, width: int, height: int, panels: int, s: Summary) -> tuple[int, int]:
    """(width, height) px of a sheet of `tiles` frames of `panels` (width x height) images each."""
    rows = -(-tiles // COLUMNS)
    grid_w = GAP + min(tiles, COLUMNS) * (panels * width + GAP)
    grid_h = GAP + rows * (HEADER + height + GAP)
    return max(grid_w, PANEL_MIN_WIDTH), grid_h + GAP + panel_rows(s) * LINE + GAP


def depth_grey(raw: np.ndarray) -> np.ndarray:
    """(h, w) uint8 of a depth image (h, w) uint16 metres*256: nearest 255 to farthest 32 on a log scale (a seabed
    from 0.5 m out to the horizon keeps its near detail), no depth (0) black."""
    out = np.zeros(raw.shape, dtype=np.uint8)
    valid = raw > 0
    if valid.any():
        d = np.log(raw[valid].astype(np.float64))
        lo, hi = d.min(), d.max()
        out[valid] = np.rint(255 - 223 * (d - lo) / (hi - lo) if hi > lo else 255).astype(np.uint8)
    return out


def instance_colours(ids: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 of instance ids (h, w) uint16: PALETTE in turn from id 1, id 0 black."""
    out = PALETTE[(ids.astype(np.int64) - 1) % len(PALETTE)]
    out[ids == 0] = 0
    return out


def draw_boxes(image: np.ndarray, boxes: list[tuple[str, tuple[int, int, int, int], tuple[int, int, int]]],
               font) -> np.ndarray:
    """(h, w, 3) uint8 copy of an RGB `image` with each (class, box, colour): a 1-px outline on the box's edge
    pixels (columns left and right over rows top..bottom, rows top and bottom over columns left..right), the class
    name above. Names go first, so no name covers an outline."""
    from PIL import Image, ImageDraw

    canvas = Image.fromarray(image)
    draw = ImageDraw.Draw(canvas)
    for name, (left, top, _, _), _ in boxes:
        draw.text((left, max(top - LINE, 0)), name, fill=TEXT, font=font)
    out = np.array(canvas)
    for _, (left, top, right, bottom), colour in boxes:  # slices, not ImageDraw: exact for 1-px-high boxes
        out[top:bottom + 1, [left, right]] = colour
        out[[top, bottom], left:right + 1] = colour
    return out


@dataclass(frozen=True)
class Tile:
    """One frame's tile, at the frame's size: its image with boxes, then depth and instances where it has them."""

    name: str  # the frame's file stem, "000123"
    image: np.ndarray  # (h, w, 3) uint8 sRGB
    boxes: tuple[tuple[str, tuple[int, int, int, int], tuple[int, int, int]], ...]  # (class, box, colour)
    depth: np.ndarray | None = None  # (h, w) uint16 metres * 256, 0 = no depth
    instance: np.ndarray | None = None  # (h, w) uint16 instance ids, 0 = terrain or water
    sonar: np.ndarray | None = None  # (fh, fw) uint16 FLS fan image (fls_fan/), drawn last by fit_size
    sonar_boxes: tuple[tuple[str, tuple[int, int, int, int], tuple[int, int, int]], ...] = ()  # fan_box of fls_label


def sonar_grey(codes: np.ndarray) -> np.ndarray:
    """(..., ) uint8 display of 16-bit sonar codes: linear, 0 black and the 99th percentile of the positive codes
    (or their maximum, if that is 0) white, brighter codes clipped; all black without a positive code."""
    positive = codes[codes > 0]
    if positive.size == 0:
        return np.zeros(codes.shape, dtype=np.uint8)
    top = float(np.percentile(positive, 99)) or float(positive.max())
    return np.rint(np.clip(codes.astype(np.float64) / top, 0.0, 1.0) * 255).astype(np.uint8)


def fit_size(width: int, height: int, box: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x, y, w, h) px: an image of (width, height) scaled by one factor to fit `box` (w, h), centred in it."""
    s = min(box[0] / width, box[1] / height)
    w, h = max(1, round(width * s)), max(1, round(height * s))
    return (box[0] - w) // 2, (box[1] - h) // 2, w, h


def class_colour(colours: dict[str, tuple[int, int, int]], name: str) -> tuple[int, int, int]:
    """The box colour of class `name`: BOX_COLOURS in turn by first sight, remembered in `colours`."""
    return colours.setdefault(name, BOX_COLOURS[len(colours) % len(BOX_COLOURS)])


def tile_size(width: int, height: int, tile_width: int = TILE_WIDTH) -> tuple[int, int]:
    """(w, h) px of a frame's panels on the sheet: the frame's size, or scaled to `tile_width` wide if wider (the
    height rounded, at least 1 px)."""
    if tile_width < 1:
        raise ExportError(f"tile width must be at least 1 px, got {tile_width}")
    if width <= tile_width:
        return width, height
    return tile_width, max(1, round(height * tile_width / width))


def scale_box(box: tuple[int, int, int, int], sx: float, sy: float, size: tuple[int, int]
              ) -> tuple[int, int, int, int]:
    """A box (left, top, right, bottom; inclusive pixel indices) of an image scaled by (sx, sy) to `size` (w, h):
    the pixels its edges [left, right + 1] x [top, bottom + 1] cover after scaling, at least one; exact at 1."""
    left, top, right, bottom = box
    w, h = size
    x0 = min(math.floor(left * sx), w - 1)
    y0 = min(math.floor(top * sy), h - 1)
    x1 = min(max(x0, math.ceil((right + 1) * sx) - 1), w - 1)
    y1 = min(max(y0, math.ceil((bottom + 1) * sy) - 1), h - 1)
    return x0, y0, x1, y1


def render_tile(tile: Tile, size: tuple[int, int], font):
    """The tile as one PIL RGB image of `size` (w, h) per panel: the image and depth box-filtered, the instances
    nearest-neighbour (so colours stay ids'), when scaled; then the boxes drawn on their scaled pixels. An FLS
    fan goes in one more panel, scaled by fit_size with its label boxes."""
    from PIL import Image

    h, w = tile.image.shape[:2]
    sw, sh = size
    panels = [(tile.image, Image.BOX)]
    if tile.depth is not None:
        panels.append((np.repeat(depth_grey(tile.depth)[..., None], 3, axis=-1), Image.BOX))
    if tile.instance is not None:
        panels.append((instance_colours(tile.instance), Image.NEAREST))
    out = Image.new("RGB", (len(panels) * sw + (tile.sonar is not None) * sw, sh))
    if tile.sonar is not None:  # the FLS fan, its shape kept, centred in the last panel on black
        fh, fw = tile.sonar.shape
        x, y, w2, h2 = fit_size(fw, fh, (sw, sh))
        fan = Image.fromarray(np.repeat(sonar_grey(tile.sonar)[..., None], 3, axis=-1)).resize((w2, h2), Image.BOX)
        boxes = [(name, scale_box(box, w2 / fw, h2 / fh, (w2, h2)), colour) for name, box, colour in tile.sonar_boxes]
        out.paste(Image.fromarray(draw_boxes(np.asarray(fan), boxes, font)), (len(panels) * sw + x, y))
    for k, (panel, resample) in enumerate(panels):
        img = Image.fromarray(np.ascontiguousarray(panel))
        if (sw, sh) != (w, h):
            img = img.resize((sw, sh), resample)
        if k == 0:
            boxes = [(name, scale_box(box, sw / w, sh / h, (sw, sh)), colour) for name, box, colour in tile.boxes]
            img = Image.fromarray(draw_boxes(np.asarray(img), boxes, font))
        out.paste(img, (k * sw, 0))
    return out


def draw_sheet(tiles: list[Tile], summary: Summary, tile_width: int = TILE_WIDTH):
    """The sheet as a PIL RGB image: tiles in rows of COLUMNS, each under its frame name, then the summary panel.
    Every tile has its first tile's size and panels."""
    from PIL import Image, ImageFont

    font = ImageFont.load_default()
    if tiles:
        h, w = tiles[0].image.shape[:2]
        size = tile_size(w, h, tile_width)
        panels = 1 + (tiles[0].depth is not None) + (tiles[0].instance is not None) + (tiles[0].sonar is not None)
    else:
        size, panels = (0, 0), 1
    sheet = Image.new("RGB", sheet_size(len(tiles), *size, panels, summary), BACKGROUND)
    _draw_grid(sheet, [(t.name, render_tile(t, size, font)) for t in tiles], *size, panels, font)
    grid_h = GAP + -(-len(tiles) // COLUMNS) * (HEADER + size[1] + GAP)
    _draw_summary(sheet, summary, grid_h + GAP, font)
    return sheet


def png_bytes(image) -> bytes:
    """The PNG file of a PIL image."""
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    return buf.getvalue()


def decode_png(data: bytes, where: str) -> np.ndarray:
    """The pixels of PNG (or JPEG: a JPEG dataset's image_2) bytes, as Pillow reads them; ExportError naming
    `where` if they are no image."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img)
    except (OSError, UnidentifiedImageError) as err:
        raise ExportError(f"{where}: cannot decode ({err})") from None


def jerlov_of(meta: object) -> str | None:
    """The Jerlov water type a frame's meta record names, or None."""
    water = meta.get("water") if isinstance(meta, dict) else None
    return None if not isinstance(water, dict) or water.get("jerlov_type") is None else str(water["jerlov_type"])


def tile_origin(k: int, width: int, height: int, panels: int) -> tuple[int, int]:
    """(x, y) px of the top-left pixel of tile k's image (below its header) on the sheet."""
    row, col = divmod(k, COLUMNS)
    return GAP + col * (panels * width + GAP), GAP + row * (HEADER + height + GAP) + HEADER


def _draw_grid(sheet, tiles, width: int, height: int, panels: int, font) -> None:
    from PIL import ImageDraw

    draw = ImageDraw.Draw(sheet)
    for k, (name, tile) in enumerate(tiles):
        x, y = tile_origin(k, width, height, panels)
        draw.text((x, y - HEADER), f"frame {name}", fill=TEXT, font=font)
        sheet.paste(tile, (x, y))


def _draw_summary(sheet, s: Summary, top: int, font) -> None:
    """The summary as text rows and horizontal bars, from y = `top` down."""
    from PIL import ImageDraw

    draw, y = ImageDraw.Draw(sheet), top
    for title, text, bars in summary_rows(s):
        draw.text((GAP, y), f"{title}: {text}" if text else title, fill=TEXT, font=font)
        y += LINE
        most = max((c for _, c in bars), default=0)
        for label, count in bars:
            draw.text((GAP + 8, y), label, fill=TEXT, font=font)
            length = round(BAR_MAX * count / most) if most else 0
            if length:
                draw.rectangle((GAP + LABEL_W, y + 2, GAP + LABEL_W + length - 1, y + LINE - 3), fill=BAR)
            draw.text((GAP + LABEL_W + length + 4, y), str(count), fill=TEXT, font=font)
            y += LINE
