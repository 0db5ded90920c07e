"""bench.scale on the CPU at a tiny size: one row per (resolution, workers) with the fields the committed table
promises, frames = workers x frames per worker, and the table, JSON and chart written."""

import json
from pathlib import Path

import pytest

from bench import scale

FIELDS = ("mode", "width", "height", "preset", "workers", "gpus", "frames", "first_frame_s", "wall_fps", "steady_fps",
          "gpu_util", "cpu_util")


def test_scale_rows_and_files(tmp_path):
    rows = scale.run(Path("examples/urchins.yaml"), resolutions=[(32, 24)], workers=[1, 2], frames_per_worker=4,
                     preset="draft", out=tmp_path, platform="egl", machine="test machine")
    assert [(r["workers"], r["frames"]) for r in rows] == [(1, 4), (2, 8)]
    for r in rows:
        assert set(FIELDS) <= set(r) and (r["mode"], r["width"], r["height"], r["preset"]) == ("cli", 32, 24, "draft")
        assert r["wall_fps"] > 0 and r["steady_fps"] > 0 and 0 <= r["cpu_util"] <= 100
        assert r["wall_fps"] == pytest.approx(r["frames"] / r["wall_s"], rel=0.02)  # wall_s is rounded to 10 ms
        assert 0 < r["first_frame_s"] <= r["wall_s"]
    saved = json.loads((tmp_path / "scale.json").read_text())
    assert saved["rows"] == rows and saved["machine"] == "test machine"
    table = (tmp_path / "scale.md").read_text()
    assert "| " + " | ".join(FIELDS) + " |" in table and table.count("| cli | 32 | 24 | draft |") == 2
    assert (tmp_path / "scale.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
