"""Scale: finished frames per second against worker processes and resolution, through the local CLI's `generate`,
with CPU and GPU utilisation sampled while each run goes.

wall_fps counts every frame over the whole run, start-up included (pool processes, GL contexts, shader and asset
variants); steady_fps is the rate after the first quarter of the frames has finished. Each run is a fresh `generate`
into an empty folder, so nothing is cached between rows except what a new process would also find (nothing).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import tempfile
import threading
import time
from pathlib import Path

from service.spec import load_spec

STEADY_AFTER = 0.25  # steady_fps counts frames finished after this share of the run's frames


def cpu_times() -> tuple[float, float]:
    """(busy, total) jiffies of all cores from /proc/stat."""
    fields = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)  # idle + iowait
    return sum(fields) - idle, sum(fields)


class GpuSampler:
    """Mean GPU utilisation (%) from nvidia-smi every `period` seconds while running; None without nvidia-smi."""

    def __init__(self, period: float = 0.5) -> None:
        self.period, self.samples = period, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self.available = shutil.which("nvidia-smi") is not None

    def _loop(self) -> None:
        while not self._stop.wait(self.period):
            try:
                out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"],
                                     capture_output=True, text=True, timeout=5).stdout.split()
                self.samples.append(statistics.mean(float(x) for x in out))
            except (OSError, ValueError, subprocess.TimeoutExpired, statistics.StatisticsError):
                pass

    def __enter__(self) -> GpuSampler:
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self.available:
            self._thread.join()

    def mean(self) -> float | None:
        return round(statistics.mean(self.samples), 1) if self.samples else None


def gpu_count() -> int:
    if shutil.which("nvidia-smi") is None:
        return 0
    out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
    return sum(line.startswith("GPU ") for line in out.splitlines())


def run_cli(spec, workers: int, platform: str) -> dict:
    """One fresh local generate of spec with `workers` processes: frames, wall and steady fps, utilisation."""
    from worker.generate import generate

    stamps: list[float] = []
    with tempfile.TemporaryDirectory() as tmp, GpuSampler() as gpu:
        busy0, total0 = cpu_times()
        t0 = time.perf_counter()
        generate(spec, Path(tmp) / "out", workers=workers, platform=platform,
                 on_frames=lambda n: stamps.extend([time.perf_counter()] * n))
        wall = time.perf_counter() - t0
        busy1, total1 = cpu_times()
    # Frames can be reported several at a time (one timestamp each): with no time between the quarter mark and the
    # end, the steady rate is the whole run's.
    k = int(len(stamps) * STEADY_AFTER)
    span = stamps[-1] - stamps[k - 1] if 0 < k < len(stamps) else 0.0
    steady = (len(stamps) - k) / span if span > 0 else len(stamps) / wall
    return {"frames": len(stamps), "wall_s": round(wall, 2), "first_frame_s": round(stamps[0] - t0, 2),
            "wall_fps": round(len(stamps) / wall, 2),
            "steady_fps": round(steady, 2), "gpu_util": gpu.mean(),
            "cpu_util": round(100.0 * (busy1 - busy0) / max(total1 - total0, 1e-9), 1)}


def run(spec_path: Path, *, resolutions: list[tuple[int, int]], workers: list[int], frames_per_worker: int,
        preset: str, out: Path | None, platform: str, machine: str | None = None) -> list[dict]:
    from bench.throughput import machine_description

    rows = []
    gpus = gpu_count()
    for width, height in resolutions:
        for n in workers:
            spec = load_spec(spec_path, {"camera.width": width, "camera.height": height, "quality": preset,
                                         "frames": n * frames_per_worker, "shard_size": frames_per_worker})
            row = {"mode": "cli", "width": width, "height": height, "preset": preset, "workers": n, "gpus": gpus,
                   **run_cli(spec, n, platform)}
            print(json.dumps(row), flush=True)
            rows.append(row)
    result = {"machine": machine or machine_description(), "spec": str(spec_path), "cores": os.cpu_count(),
              "rows": rows}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "scale.json").write_text(json.dumps(result, indent=1) + "\n")
        (out / "scale.md").write_text(format_table(result) + "\n")
        chart(result).save(out / "scale.png")
    print(format_table(result))
    return rows


def format_table(r: dict) -> str:
    cols = ("mode", "width", "height", "preset", "workers", "gpus", "frames", "first_frame_s", "wall_fps", "steady_fps",
            "gpu_util", "cpu_util")
    return "\n".join([
        f"# Scale: {r['spec']}", "", f"machine: {r['machine']} ({r['cores']} cores)  ",
        f"first_frame_s: seconds until the first frame is written; wall_fps: frames over the whole run, start-up "
        f"included; steady_fps: after the first {int(STEADY_AFTER * 100)}% of the frames; gpu_util / cpu_util: mean % "
        "over the run (cpu: all cores)", "",
        "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols),
        *["| " + " | ".join("" if row[c] is None else str(row[c]) for c in cols) + " |" for row in r["rows"]],
    ])


def chart(r: dict):
    """Frames per second (wall solid, steady hollow) against workers, one colour per resolution."""
    from PIL import Image, ImageDraw

    W, H, pad = 640, 400, 50
    img = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(img)
    rows = r["rows"]
    xmax = max(row["workers"] for row in rows)
    ymax = max(max(row["wall_fps"], row["steady_fps"]) for row in rows) * 1.1 or 1.0
    d.line([(pad, H - pad), (W - 10, H - pad)], fill="black")
    d.line([(pad, 10), (pad, H - pad)], fill="black")
    d.text((W // 2 - 20, H - 20), "workers", fill="black")
    d.text((5, 5), f"fps (max {ymax / 1.1:.1f})", fill="black")
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e"]
    sizes = sorted({(row["width"], row["height"]) for row in rows}, reverse=True)
    for k, size in enumerate(sizes):
        c = colours[k % len(colours)]
        pts = sorted((row["workers"], row["wall_fps"], row["steady_fps"]) for row in rows
                     if (row["width"], row["height"]) == size)
        xy = [(pad + (W - pad - 20) * n / xmax, H - pad - (H - pad - 20) * f / ymax) for n, f, _ in pts]
        if len(xy) > 1:
            d.line(xy, fill=c, width=2)
        for (n, _, s), (x, y) in zip(pts, xy):
            d.ellipse([x - 3, y - 3, x + 3, y + 3], fill=c)
            ys = H - pad - (H - pad - 20) * s / ymax
            d.ellipse([x - 3, ys - 3, x + 3, ys + 3], outline=c)
            d.text((x - 4, H - pad + 4), str(n), fill="black")
        d.text((W - 160, 15 + 14 * k), f"{size[0]}x{size[1]}", fill=c)
    return img
