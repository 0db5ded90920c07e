"""Scale: finished frames per second against worker processes, GPUs and resolution, through the local CLI's
`generate` (mode cli) and through the service on this machine (mode service, seasynth.bench.scale_service), with CPU and GPU
utilisation sampled while each run goes.

wall_fps counts every frame over the whole run: for cli, start-up included (pool processes, GL contexts, shader and
asset variants); for service, from POST /datasets to the status read that says it succeeded, with the workers
already up (they are long-lived). steady_fps is the rate after the first quarter of the frames has finished (for
service, of whole shards as the status shows them). `gpus` is the number of GPUs the rendering processes used: with
--gpus G, workers are bound to the first G GPUs round robin (seasynth.service.gpus); without, to EGL's default device (1 if
that is a GPU, 0 on a software renderer). Each run is fresh (a new generate into an empty folder, a new service
stack), so nothing is cached between rows except what a new process would also find (nothing).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

from seasynth.bench.meters import STEADY_AFTER, CpuMeter, GpuSampler, rates
from seasynth.bench.scale_service import run_service, service_shard_size
from seasynth.service.gpus import GpuChoice
from seasynth.service.spec.dataset import load_spec


def run_cli(spec, workers: int, platform: str, gpus: GpuChoice | None = None) -> dict:
    """One fresh local generate of spec with `workers` processes: frames, wall and steady fps, utilisation."""
    from seasynth.worker.local.generate import generate

    stamps: list[float] = []
    with tempfile.TemporaryDirectory() as tmp, GpuSampler() as gpu, CpuMeter() as cpu:
        t0 = time.perf_counter()
        generate(spec, Path(tmp) / "out", workers=workers, platform=platform, gpus=gpus,
                 on_frames=lambda n: stamps.extend([time.perf_counter()] * n))
        wall = time.perf_counter() - t0
    stop_fork_server()
    return {"frames": len(stamps), **rates(stamps, t0, wall), "gpu_util": gpu.mean(), "cpu_util": cpu.util}


def stop_fork_server() -> None:
    """Stop this process's fork server (seasynth.worker.local.pool_start), so the next row starts its processes as a new
    `seasynth generate` would: the server's imports are part of start-up."""
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    if server is not None and hasattr(server, "_stop"):  # CPython's own; without it rows after the first start warm
        server._stop()


def gpus_used(platform: str, gpus: GpuChoice | None, workers: int) -> int:
    """GPUs that `workers` render processes bound by `gpus` use (not GPUs present)."""
    from seasynth.worker.render.devices import egl_devices, resolve_gpus

    if platform != "egl":
        return 0
    if gpus is None:  # EGL's default device: the first one it lists
        devices = egl_devices()
        return int(bool(devices) and devices[0].is_gpu)
    return min(len(resolve_gpus(gpus, platform)), workers)


def check_gpus(gpu_counts: list[int] | None, platform: str) -> None:
    """Before any row: every count of --gpus is available here (an unattended run fails in seconds, not hours)."""
    from seasynth.worker.render.devices import gpu_indices

    if not gpu_counts:
        return
    found = gpu_indices() if platform == "egl" else []
    if max(gpu_counts) > len(found):
        raise SystemExit(f"--gpus {','.join(map(str, gpu_counts))}: EGL finds {len(found)} GPU device(s) on this "
                         f"machine (platform {platform}); on an NVIDIA host check __EGL_VENDOR_LIBRARY_FILENAMES "
                         "points at the driver's EGL vendor file")


def run(spec_path: Path, *, resolutions: list[tuple[int, int]], workers: list[int], frames_per_worker: int,
        preset: str, out: Path | None, platform: str, machine: str | None = None, modes: tuple[str, ...] = ("cli",),
        gpu_counts: list[int] | None = None, storage: str = "s3") -> list[dict]:
    """One row per (resolution, GPU count, workers, mode); also scale.json, .md and .png in `out` when given."""
    from seasynth.bench.throughput import machine_description

    check_gpus(gpu_counts, platform)
    if "service" in modes:
        from seasynth.bench.stack import find_program

        find_program("redis-server", "apt-get install -y redis-server")  # before the first row, not mid-run
    rows = []
    choices = [GpuChoice(count=g) for g in gpu_counts] if gpu_counts else [None]
    for width, height in resolutions:
        for choice in choices:
            for n in workers:
                for mode in modes:
                    over = {"camera.width": width, "camera.height": height, "quality": preset,
                            "frames": n * frames_per_worker}
                    if mode == "service":  # the local generate has no shards: the spec's own stands there
                        over["shard_size"] = service_shard_size(frames_per_worker, width * height)
                    spec = load_spec(spec_path, over)
                    measured = (run_cli(spec, n, platform, choice) if mode == "cli"
                                else run_service(spec, n, platform, choice, storage))
                    row = {"mode": mode, "width": width, "height": height, "preset": preset, "workers": n,
                           "gpus": gpus_used(platform, choice, n), **measured}
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
        "mode cli: a fresh `seasynth generate`, start-up included; mode service: POST /datasets to the status read "
        "that says succeeded, through redis-server, an S3 server, the API and one Celery worker of `workers` render "
        "processes started beforehand (shards seen through the status, polled every 0.1 s). first_frame_s: seconds "
        "until the first frame is written (service: the first shard committed); wall_fps: frames over the whole run; "
        f"steady_fps: after the first {int(STEADY_AFTER * 100)}% of the frames; gpus: GPUs the workers used; "
        "gpu_util / cpu_util: mean % over the run (gpu: all GPUs present; cpu: all cores)", "",
        "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols),
        *["| " + " | ".join("" if row[c] is None else str(row[c]) for c in cols) + " |" for row in r["rows"]],
    ])


def chart(r: dict):
    """Frames per second (wall solid, steady hollow) against workers, one colour per resolution, mode and GPU
    count."""
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
    series = sorted({(row["width"], row["height"], row["mode"], row["gpus"]) for row in rows}, reverse=True)
    for k, key in enumerate(series):
        c = colours[k % len(colours)]
        pts = sorted((row["workers"], row["wall_fps"], row["steady_fps"]) for row in rows
                     if (row["width"], row["height"], row["mode"], row["gpus"]) == key)
        xy = [(pad + (W - pad - 20) * n / xmax, H - pad - (H - pad - 20) * f / ymax) for n, f, _ in pts]
        if len(xy) > 1:
            d.line(xy, fill=c, width=2)
        for (n, _, s), (x, y) in zip(pts, xy):
            d.ellipse([x - 3, y - 3, x + 3, y + 3], fill=c)
            ys = H - pad - (H - pad - 20) * s / ymax
            d.ellipse([x - 3, ys - 3, x + 3, ys + 3], outline=c)
            d.text((x - 4, H - pad + 4), str(n), fill="black")
        d.text((W - 200, 15 + 14 * k), f"{key[0]}x{key[1]} {key[2]} {key[3]} GPU", fill=c)
    return img
