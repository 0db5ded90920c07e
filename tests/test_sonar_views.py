"""`seasynth waterfall` and the FLS panel of `seasynth preview`: the waterfall's rows are the sss/ rows in frame
order, its box outlines are exactly the runs of sss_label/ spans; the preview's sonar panel is the fan image with
exactly its fls_label fan boxes outlined."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from local_datasets import seasynth
from PIL import Image

from seasynth.service.errors import ExportError
from seasynth.service.sheet import (
    BOX_COLOURS,
    COLUMNS,
    GAP,
    HEADER,
    LINE,
    PANEL_MIN_WIDTH,
    fit_size,
    scale_box,
    sonar_grey,
    summary_rows,
    tile_origin,
)
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import frame_paths
from seasynth.worker.local.folder import RECORD
from seasynth.worker.local.generate import generate
from seasynth.worker.preview.sheet import make_preview

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "survey-sonar.yaml"
W, H, FRAMES, BINS = 48, 36, 10, 48
SMALL = {"camera.width": W, "camera.height": H, "frames": FRAMES, "shard_size": 5, "sensors.fls.beams": 32,
         "sensors.fls.range_bins": 48, "sensors.fls.horizontal_aperture_deg": 90.0, "sensors.fls.beam_width_deg": 2.0,
         "sensors.fls.range_m": [0.5, 8.0], "sensors.sss.enabled": True, "sensors.sss.range_bins": BINS,
         "sensors.sss.horizontal_beam_deg": 2.0, "sensors.dvl.enabled": False,
         "sensors.imu.enabled": False, "sensors.pressure.enabled": False}
COLOUR = np.array(BOX_COLOURS[0], dtype=np.uint8)


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sonar-views") / "ds"
    generate(load_spec(EXAMPLE, SMALL), out, workers=1)
    return out


def test_sensor_files_are_the_frame_paths_resume_checks(survey):
    spec = load_spec(EXAMPLE, SMALL)
    written = {p.relative_to(survey).as_posix() for p in survey.rglob("*") if p.is_file()} - {RECORD}
    folders = ("image_2", "label_2", "calib", "meta", "fls", "fls_fan", "fls_label", "sss", "sss_label")
    suffix = {"image_2": ".png", "fls": ".png", "fls_fan": ".png", "sss": ".png", "calib": ".txt", "label_2": ".txt"}
    assert written == {f"{d}/{i:06d}{suffix.get(d, '.json')}" for i in range(FRAMES) for d in folders}
    assert {p for i in range(FRAMES) for p in frame_paths(spec, i)} == written


def outline_mask(shape: tuple[int, int], boxes) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    for left, top, right, bottom in boxes:
        m[top:bottom + 1, [left, right]] = True
        m[[top, bottom], left:right + 1] = True
    return m


def test_sonar_grey_maps_the_99th_percentile_of_positive_codes_to_white():
    codes = np.arange(0, 101, dtype=np.uint16)  # positive codes 1..100: 99th percentile 99.01
    g = sonar_grey(codes)
    assert g[0] == 0 and g[100] == 255 and g[99] == 255 and g[50] == round(50 / 99.01 * 255)
    assert not sonar_grey(np.zeros((2, 3), np.uint16)).any()


def test_waterfall_stacks_the_rows_in_frame_order_with_the_label_runs_outlined(survey, tmp_path):
    rows = np.concatenate([np.asarray(Image.open(survey / f"sss/{i:06d}.png")) for i in range(FRAMES)])
    assert rows.shape == (FRAMES, 2 * BINS) and rows.dtype == np.uint16
    r = seasynth("waterfall", survey, "--out", tmp_path / "plain.png")
    assert r.returncode == 0, r.stderr
    plain = np.asarray(Image.open(tmp_path / "plain.png"))
    assert np.array_equal(plain, np.repeat(sonar_grey(rows)[..., None], 3, axis=-1))

    r = seasynth("waterfall", survey, "--out", tmp_path / "wf.png", "--labels", "--row-height", "3")
    assert r.returncode == 0, r.stderr
    image = np.asarray(Image.open(tmp_path / "wf.png"))
    assert image.shape == (3 * FRAMES, 2 * BINS, 3)
    # Each run of consecutive frames in which an instance is labelled on one side: one box over those rows.
    seen: dict[tuple[int, str], list[tuple[int, int, int]]] = {}
    for i in range(FRAMES):
        for o in json.loads((survey / f"sss_label/{i:06d}.json").read_text())["objects"]:
            seen.setdefault((o["instance_id"], o["side"]), []).append((i, o["column_min"], o["column_max"]))
    boxes = []
    for spans in seen.values():
        runs = [[spans[0]]]
        for s in spans[1:]:
            (runs[-1] if s[0] == runs[-1][-1][0] + 1 else runs.append([]) or runs[-1]).append(s)
        for run in runs:
            boxes.append((min(s[1] for s in run), 3 * run[0][0], max(s[2] for s in run), 3 * run[-1][0] + 2))
    assert boxes, "no target in the side-scan swath: the check would be empty"
    outline = outline_mask((3 * FRAMES, 2 * BINS), boxes)
    assert np.array_equal((image == COLOUR).all(-1), outline)
    grey = np.repeat(np.repeat(sonar_grey(rows), 3, axis=0)[..., None], 3, axis=-1)
    text = np.zeros(outline.shape, dtype=bool)  # each class name's rows above its box (as tests/test_preview.py)
    for left, top, _, _ in boxes:
        text[max(top - LINE, 0):max(top - LINE, 0) + LINE, left:] = True
    assert ((image == grey).all(-1) | outline | text).all()
    assert r.stdout == f"{tmp_path / 'wf.png'}: {FRAMES} pings x {2 * BINS} bins, {len(boxes)} target boxes\n"


def test_waterfall_refuses_a_dataset_without_side_scan_naming_the_field(survey, tmp_path):
    from seasynth.worker.preview.waterfall import write_waterfall

    ds = tmp_path / "no-sss"
    generate(load_spec(EXAMPLE, {**SMALL, "frames": 1, "sensors.sss.enabled": False}), ds, workers=1)
    with pytest.raises(ExportError, match=r"no side-scan sonar \(sensors\.sss\.enabled is false\)"):
        write_waterfall(ds, tmp_path / "w.png")
    with pytest.raises(ExportError, match="ending in .png"):
        write_waterfall(survey, tmp_path / "w.jpg")
    (survey / "sss/000003.png").rename(tmp_path / "moved.png")
    try:
        with pytest.raises(ExportError, match=r"sss/000003\.png: missing"):
            write_waterfall(survey, tmp_path / "w.png")
    finally:
        (tmp_path / "moved.png").rename(survey / "sss/000003.png")
    assert not (tmp_path / "w.png").exists()


def test_preview_shows_the_fls_fan_with_exactly_its_label_boxes(survey, tmp_path):
    p = make_preview(survey, tmp_path / "sheet.png", frames=FRAMES)
    sheet = np.asarray(Image.open(p.sheet))
    rows = -(-FRAMES // COLUMNS)
    panel_rows = sum(1 + len(bars) for _, _, bars in summary_rows(p.summary))
    assert sheet.shape == (GAP + rows * (HEADER + H + GAP) + GAP + panel_rows * LINE + GAP,
                           max(GAP + COLUMNS * (2 * W + GAP), PANEL_MIN_WIDTH), 3)
    boxes_seen = 0
    for k in range(FRAMES):
        fan = np.asarray(Image.open(survey / f"fls_fan/{k:06d}.png"))
        fh, fw = fan.shape
        x, y, w, h = fit_size(fw, fh, (W, H))
        x0, y0 = tile_origin(k, W, H, 2)
        panel = sheet[y0:y0 + H, x0 + W:x0 + 2 * W]
        inside = np.zeros((H, W), dtype=bool)
        inside[y:y + h, x:x + w] = True
        assert (panel[~inside] == 0).all()  # black around the fan, which keeps its shape
        labels = json.loads((survey / f"fls_label/{k:06d}.json").read_text())["objects"]
        boxes = [scale_box(tuple(o["fan_box"][s] for s in ("left", "top", "right", "bottom")), w / fw, h / fh, (w, h))
                 for o in labels]
        boxes_seen += len(boxes)
        outline = np.zeros((H, W), dtype=bool)
        outline[y:y + h, x:x + w] = outline_mask((h, w), boxes)
        assert np.array_equal((panel == COLOUR).all(-1), outline)
        # Elsewhere in the fan: its grey (r = g = b), or the class names' (white, antialiased: grey too).
        drawn = panel[inside & ~outline]
        assert ((drawn[:, 0] == drawn[:, 1]) & (drawn[:, 1] == drawn[:, 2])).all()
    assert boxes_seen > 0
