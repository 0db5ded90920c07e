"""seasynth.bench.scale on the CPU at a tiny size, both modes: one row per (resolution, workers, mode) with the fields the
committed table promises, frames = workers x frames per worker, every frame the service counted in the bucket, and
the table, JSON and chart written."""

import json
from pathlib import Path

import pytest
from local_datasets import closed_form_example

from seasynth.bench import meters, scale
from seasynth.bench.scale_service import service_shard_size

FIELDS = ("mode", "width", "height", "preset", "workers", "gpus", "frames", "first_frame_s", "wall_fps", "steady_fps",
          "gpu_util", "cpu_util")


def test_scale_rows_and_files(tmp_path):
    # The bench's rows are under test, not the light: the example with the water's closed form, whose frames need no
    # column solves (the example's Jerlov types under random suns meet hundreds; CI's 2-core machine timed out on them).
    rows = scale.run(closed_form_example(tmp_path), resolutions=[(32, 24)], workers=[1, 2], frames_per_worker=4,
                     preset="draft", out=tmp_path, platform="egl", machine="test machine", modes=("cli", "service"))
    assert [(r["mode"], r["workers"], r["frames"]) for r in rows] == [
        ("cli", 1, 4), ("service", 1, 4), ("cli", 2, 8), ("service", 2, 8)]
    for r in rows:
        assert set(FIELDS) <= set(r) and (r["width"], r["height"], r["preset"]) == (32, 24, "draft")
        assert r["gpus"] == 0  # EGL's default device here is Mesa's software renderer: no GPU used
        assert r["wall_fps"] > 0 and r["steady_fps"] > 0 and 0 <= r["cpu_util"] <= 100
        assert r["wall_fps"] == pytest.approx(r["frames"] / r["wall_s"], rel=0.02)  # wall_s is rounded to 10 ms
        assert 0 < r["first_frame_s"] <= r["wall_s"]
    for r in rows[1::2]:  # the service: every frame counted is in the bucket, in shards of a fifth of a worker's
        assert r["frames_stored"] == r["frames"] and r["shard_size"] == service_shard_size(4) == 1
    saved = json.loads((tmp_path / "scale.json").read_text())
    assert saved["rows"] == rows and saved["machine"] == "test machine"
    table = (tmp_path / "scale.md").read_text()
    assert "| " + " | ".join(FIELDS) + " |" in table
    assert table.count("| cli | 32 | 24 | draft |") == 2 and table.count("| service | 32 | 24 | draft |") == 2
    assert (tmp_path / "scale.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_rates_count_the_steady_part_after_a_quarter_of_the_frames():
    # 8 frames: two at 1 s, then one a second from 2 s to 7 s; the steady part is frames 3..8 after the 2nd one.
    stamps = [1.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    got = meters.rates(stamps, t0=0.0, wall=8.0)
    assert got == {"wall_s": 8.0, "first_frame_s": 1.0, "wall_fps": 1.0, "steady_fps": 1.0,
                   "done_at_s": {"10": 1.0, "25": 1.0, "50": 3.0, "75": 5.0, "90": 7.0, "100": 7.0}}
    assert meters.rates([2.0, 2.0], t0=0.0, wall=4.0)["steady_fps"] == 0.5  # no span: the whole run's rate


def test_more_gpus_than_found_stop_before_any_row(monkeypatch):
    from seasynth.worker.render import devices

    monkeypatch.setattr(devices, "gpu_indices", lambda: [0])
    with pytest.raises(SystemExit, match="--gpus 1,2: EGL finds 1 GPU device"):
        scale.run(Path("examples/urchins.yaml"), resolutions=[(32, 24)], workers=[1], frames_per_worker=4,
                  preset="draft", out=None, platform="egl", gpu_counts=[1, 2])
    monkeypatch.setattr(devices, "gpu_indices", lambda: [0, 1])
    from seasynth.service.gpus import GpuChoice

    assert [scale.gpus_used("egl", GpuChoice(count=2), n) for n in (1, 2, 16)] == [1, 2, 2]
    assert scale.gpus_used("osmesa", None, 4) == 0


def test_service_shards_are_a_fifth_of_a_worker_within_the_spec_limit():
    from seasynth.service.spec.dataset import MAX_SHARD_MEGAPIXELS

    assert [service_shard_size(n) for n in (1, 4, 5, 6, 125, 400)] == [1, 1, 1, 2, 25, 80]
    assert service_shard_size(400, 1920 * 1080) == 80  # 166 megapixels: within the limit
    assert service_shard_size(400, 3840 * 2160) == 72 == int(MAX_SHARD_MEGAPIXELS * 1e6 // (3840 * 2160))
    assert service_shard_size(400, 10**9) == 1  # a frame over the limit alone still makes a shard (the spec says)
