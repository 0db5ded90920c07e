"""`seasynth preview`: the sheet is laid out as documented, boxes sit on their KITTI edges, and the summary equals
counts taken again from label_2 and meta/."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from local_datasets import generate_variants, seasynth
from PIL import Image

from seasynth.service.errors import ExportError
from seasynth.service.sheet import (
    BOX_COLOURS,
    COLUMNS,
    GAP,
    HEADER,
    HEIGHT_EDGES,
    LINE,
    PANEL_MIN_WIDTH,
    markdown,
    summary_rows,
    tile_origin,
)
from seasynth.worker.frame import kitti
from seasynth.worker.preview.sheet import make_preview

W, H, FRAMES = 48, 36, 5


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    """The same frames with depth/ and instance/, and without."""
    return generate_variants(tmp_path_factory.mktemp("datasets"), {"camera.width": W, "camera.height": H,
                                                                    "frames": FRAMES},
                             {"full": ({"outputs.depth": True, "outputs.instance": True}, 1), "plain": ({}, 1)})


def label_truth(ds: Path) -> list[list[dict]]:
    return [kitti.parse_label_file((ds / f"label_2/{i:06d}.txt").read_text()) for i in range(FRAMES)]


@pytest.mark.parametrize(("name", "panels", "shown"), [("full", 3, 3), ("plain", 1, 5)])
def test_sheet_size_and_boxes_on_their_kitti_edges(datasets, tmp_path, name, panels, shown):
    ds = datasets[name]
    p = make_preview(ds, tmp_path / "sheet.png", frames=shown)
    assert p.tiles == shown and p.sheet == tmp_path / "sheet.png" and p.table == tmp_path / "sheet.md"
    sheet = np.asarray(Image.open(p.sheet))
    rows = -(-shown // COLUMNS)
    panel_rows = sum(1 + len(bars) for _, _, bars in summary_rows(p.summary))
    width = max(GAP + min(shown, COLUMNS) * (panels * W + GAP), PANEL_MIN_WIDTH)
    height = GAP + rows * (HEADER + H + GAP) + GAP + panel_rows * LINE + GAP
    assert sheet.shape == (height, width, 3)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["sheet.md", "sheet.png"]  # no temporary left
    colour = np.array(BOX_COLOURS[0], dtype=np.uint8)
    boxes_seen = 0
    for k, lines in enumerate(label_truth(ds)[:shown]):
        x0, y0 = tile_origin(k, W, H, panels)
        tile = sheet[y0:y0 + H, x0:x0 + panels * W]
        outline = np.zeros((H, W), dtype=bool)
        for line in lines:
            left, top, right, bottom = (int(v) for v in line["bbox"])
            outline[top:bottom + 1, [left, right]] = True
            outline[[top, bottom], left:right + 1] = True
            boxes_seen += 1
        # Exactly the outline pixels of the frame's KITTI boxes have the box colour in the image panel.
        assert np.array_equal((tile[:, :W] == colour).all(axis=-1), outline)
        # Every other pixel is the frame's image, except in the class names' rows above each box.
        image = np.asarray(Image.open(ds / f"image_2/{k:06d}.png"))[..., :3]
        text = np.zeros((H, W), dtype=bool)
        for line in lines:
            left, top = int(line["bbox"][0]), int(line["bbox"][1])
            text[max(top - LINE, 0):max(top - LINE, 0) + LINE, left:] = True
        assert ((tile[:, :W] == image).all(-1) | outline | text).all()
        if panels == 3:
            depth = np.asarray(Image.open(ds / f"depth/{k:06d}.png"))
            ids = np.asarray(Image.open(ds / f"instance/{k:06d}.png"))
            grey = tile[:, W:2 * W]
            assert (grey[..., 0] == grey[..., 1]).all() and (grey[..., 0] == grey[..., 2]).all()
            assert np.array_equal(grey[..., 0] == 0, depth == 0)
            if (depth > 0).any():
                assert grey[..., 0].max() == 255 and grey[depth == depth[depth > 0].min(), 0].min() == 255
            inst = tile[:, 2 * W:]
            assert np.array_equal((inst == 0).all(-1), ids == 0)
            for i in np.unique(ids[ids > 0]):  # one colour per id
                assert len(np.unique(inst[ids == i], axis=0)) == 1
    assert boxes_seen > 0  # the check above drew at least one box


@pytest.mark.parametrize("name", ["full", "plain"])
def test_summary_equals_counts_from_label_files(datasets, tmp_path, name):
    ds = datasets[name]
    s = make_preview(ds, tmp_path / "s.png", frames=2).summary
    objects = [o for lines in label_truth(ds) for o in lines]
    heights = [int(o["bbox"][3] - o["bbox"][1] + 1) for o in objects]
    classes: dict[str, int] = {}
    for o in objects:
        classes[o["type"]] = classes.get(o["type"], 0) + 1
    assert s.frames == FRAMES and s.objects == len(objects) > 0
    assert s.objects_per_class == classes
    assert sum(s.height_hist) == len(objects)
    assert list(s.height_hist) == [sum(lo <= h < hi for h in heights)
                                   for lo, hi in zip(HEIGHT_EDGES, HEIGHT_EDGES[1:] + (10**9,))]
    assert s.truncated == sum(o["truncated"] > 0 for o in objects)
    assert list(s.occluded) == [sum(o["occluded"] == lv for o in objects) for lv in range(4)]
    water: dict[str, int] = {}
    for i in range(FRAMES):
        t = json.loads((ds / f"meta/{i:06d}.json").read_text())["water"]["jerlov_type"]
        water[t] = water.get(t, 0) + 1
    assert s.jerlov == dict(sorted(water.items())) and sum(s.jerlov.values()) == FRAMES
    table = (tmp_path / "s.md").read_text()
    assert table == markdown(s)
    for cls, n in classes.items():
        assert f"| objects per class: {cls} | {n} (" in table
    for t in water:
        assert f"| Jerlov water type: {t} |" in table
    assert f"| frames | {FRAMES} frames, {len(objects)} objects |" in table


def test_cli_prints_the_table_and_refuses_bad_input(datasets, tmp_path):
    r = seasynth("preview", datasets["full"], "--out", tmp_path / "a.png", "--frames", "2")
    assert r.returncode == 0, r.stderr
    table = (tmp_path / "a.md").read_text()
    assert table in r.stdout and Image.open(tmp_path / "a.png").format == "PNG"
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.md", "a.png"]  # no temporary left behind
    for bad in ("0", "-3"):
        r = seasynth("preview", datasets["full"], "--out", tmp_path / "b.png", "--frames", bad)
        assert r.returncode == 2 and "Invalid value for '--frames'" in r.stderr and "Traceback" not in r.stderr
    r = seasynth("preview", tmp_path / "nowhere", "--out", tmp_path / "c.png")
    assert (r.returncode, r.stderr) == (1, f"error: {tmp_path / 'nowhere'}: no such dataset folder\n")
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.md", "a.png"]


def test_library_refuses_bad_frame_counts_and_names(datasets, tmp_path):
    for n in (0, -1):
        with pytest.raises(ExportError, match="--frames must be at least 1"):
            make_preview(datasets["plain"], tmp_path / "s.png", frames=n)
    with pytest.raises(ExportError, match="ending in .png"):
        make_preview(datasets["plain"], tmp_path / "s.jpg")
    with pytest.raises(ExportError, match="no such folder"):
        make_preview(datasets["plain"], tmp_path / "missing" / "s.png")
    assert list(tmp_path.iterdir()) == []


def test_wide_frames_are_scaled_to_the_tile_width_with_their_boxes(datasets, tmp_path):
    """Tiles of frames wider than --tile-width are scaled down, and each box outline lands on the pixels its box's
    edges cover after scaling: exactly those pixels have the box colour in the image panel."""
    from seasynth.service.sheet import scale_box, tile_size

    ds, tw = datasets["full"], 24
    w, h = tile_size(W, H, tw)
    assert (w, h) == (24, 18)
    p = make_preview(ds, tmp_path / "sheet.png", frames=FRAMES, tile_width=tw)
    sheet = np.asarray(Image.open(p.sheet))
    panel_rows = sum(1 + len(bars) for _, _, bars in summary_rows(p.summary))
    rows = -(-FRAMES // COLUMNS)
    assert sheet.shape == (GAP + rows * (HEADER + h + GAP) + GAP + panel_rows * LINE + GAP,
                           max(GAP + COLUMNS * (3 * w + GAP), PANEL_MIN_WIDTH), 3)
    colour = np.array(BOX_COLOURS[0], dtype=np.uint8)
    for k, lines in enumerate(label_truth(ds)):
        x0, y0 = tile_origin(k, w, h, 3)
        outline = np.zeros((h, w), dtype=bool)
        for line in lines:
            left, top, right, bottom = scale_box(tuple(int(v) for v in line["bbox"]), w / W, h / H, (w, h))
            outline[top:bottom + 1, [left, right]] = True
            outline[[top, bottom], left:right + 1] = True
        assert np.array_equal((sheet[y0:y0 + h, x0:x0 + w] == colour).all(axis=-1), outline)
        ids = np.asarray(Image.open(ds / f"instance/{k:06d}.png"))
        inst = sheet[y0:y0 + h, x0 + 2 * w:x0 + 3 * w]
        # Nearest-neighbour: each scaled pixel takes the id at its centre's place in the frame.
        nearest = ids[((np.arange(h) + 0.5) * H / h).astype(int)][:, ((np.arange(w) + 0.5) * W / w).astype(int)]
        assert np.array_equal((inst == 0).all(-1), nearest == 0)
        for i in np.unique(nearest[nearest > 0]):  # one colour per id, as at native size
            assert len(np.unique(inst[nearest == i], axis=0)) == 1


def test_scale_box_is_exact_at_scale_one_and_keeps_boxes_inside():
    from seasynth.service.sheet import scale_box, tile_size

    assert scale_box((3, 4, 10, 20), 1.0, 1.0, (48, 36)) == (3, 4, 10, 20)
    assert scale_box((0, 0, 0, 0), 0.1, 0.1, (5, 4)) == (0, 0, 0, 0)  # a 1-px box stays one pixel
    assert scale_box((40, 30, 47, 35), 0.5, 0.5, (24, 18)) == (20, 15, 23, 17)
    # A 1920x1080 dataset's sheet of 12 frames with depth and instances stays a few thousand pixels wide.
    w, h = tile_size(1920, 1080)
    assert (w, h) == (320, 180) and GAP + COLUMNS * (3 * w + GAP) < 4000
