"""Where a textured frame's time goes at 1920x1080 on one GPU, beside the untextured frame (materials.procedural
off: vertex colours, the frames of the code before textures), in one run:

1. One render process (a RenderSession, as a `generate` worker has) renders the same frames of each spec twice:
   first as a new process meets them (its uploads, shader builds and terrain texture coordinates), then again
   (steady). Each piece of `frame_files` is timed by wall clock and by this process's CPU time: sampling the scene,
   its draw list, the GL render (passes queued and read back), labels (the objects drawn alone), meta, encoding.
   GL work is not waited for between pieces: it shows where the process waits for it (the render's read-back).
2. The steady pass again under cProfile: the functions where each mode spends its time (profile-MODE.txt).
3. Whole `seasynth generate` commands (off, on, off, on) with `--timeline`: per render process, its start-up, its
   first frame, and the median period between its frames written after its third.

    python3 bench/results/gpu/frame-time/measure.py OUT [--frames N] [--whole-frames N] [--pairs N] [--size WxH]

Run from the repo root with seasynth importable; SEASYNTH_CACHE_DIR as the environment sets it (a warm-up command
of each mode fills it first, so no whole command solves a water column). Writes OUT/frame-time.json.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import itertools
import json
import os
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import yaml

EXAMPLE = Path("examples/urchins.yaml")
PIECES = ("scene", "draw_items", "render", "labels", "meta", "encode")


def spec_file(mode: str, tmp: Path) -> Path:
    if mode == "on":
        return EXAMPLE
    data = yaml.safe_load(EXAMPLE.read_text())
    path = tmp / "urchins-untextured.yaml"
    path.write_text(yaml.safe_dump({**data, "materials": {**data.get("materials", {}), "procedural": False}}))
    return path


def timed_session(session, clocks: dict[str, list[list[float]]]):
    """Wrap the session's pieces so that each call adds [wall s, CPU s] to clocks[piece][-1]."""
    import seasynth.worker.frame.function as fn

    def wrap(name: str, f):
        def timed(*a, **k):
            w, c = time.perf_counter(), time.process_time()
            try:
                return f(*a, **k)
            finally:
                got = (clocks[name] or [[0.0, 0.0]])[-1]  # the profiled pass keeps no clocks
                got[0] += time.perf_counter() - w
                got[1] += time.process_time() - c
        return timed

    session.scene = wrap("scene", session.scene)
    session.draw_items = wrap("draw_items", session.draw_items)
    session._renderer.render = wrap("render", session._renderer.render)
    session.labels = wrap("labels", session.labels)
    session.meta = wrap("meta", session.meta)
    fn.encode_image = wrap("encode", fn.encode_image)
    fn.png_bytes = wrap("encode", fn.png_bytes)


def one_process(mode: str, spec_path: Path, frames: int, size: tuple[int, int], out: Path) -> dict:
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import RenderSession
    from seasynth.worker.scene import disk_cache

    spec = load_spec(spec_path, {"camera.width": size[0], "camera.height": size[1], "frames": frames})
    clocks: dict[str, list[list[float]]] = defaultdict(list)
    passes = {}
    with disk_cache.run_folder() as folder:
        disk_cache.share_in(folder)
        with RenderSession(platform="egl", variant_folder=folder) as session:
            timed_session(session, clocks)
            for name in ("first", "steady"):
                totals = []
                for i in range(frames):
                    for piece in PIECES:
                        clocks[piece].append([0.0, 0.0])
                    w, c = time.perf_counter(), time.process_time()
                    session.frame_files(spec, i)
                    totals.append([time.perf_counter() - w, time.process_time() - c])
                passes[name] = summary(clocks, totals)
                clocks.clear()
            prof = cProfile.Profile()
            prof.enable()
            for i in range(frames):
                session.frame_files(spec, i)
            prof.disable()
            text = io.StringIO()
            pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(30)
            (out / f"profile-{mode}.txt").write_text(text.getvalue())
            passes["renderer"] = session.renderer_name
    return passes


def summary(clocks: dict[str, list[list[float]]], totals: list[list[float]]) -> dict:
    """Mean ms per frame of each piece and of the whole frame, wall and CPU; `other`: the frame less its pieces."""
    def mean_ms(rows: list[list[float]], k: int) -> float:
        return round(1e3 * statistics.fmean(r[k] for r in rows), 2)

    out = {p: {"wall_ms": mean_ms(clocks[p], 0), "cpu_ms": mean_ms(clocks[p], 1)} for p in PIECES}
    out["frame"] = {"wall_ms": mean_ms(totals, 0), "cpu_ms": mean_ms(totals, 1)}
    out["other"] = {k: round(out["frame"][k] - sum(out[p][k] for p in PIECES), 2) for k in ("wall_ms", "cpu_ms")}
    return out


def whole(spec_path: Path, frames: int, size: tuple[int, int], out: Path, timeline: Path) -> dict:
    timeline.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "seasynth.cli", "generate", str(spec_path), "--out", str(out), "--frames",
           str(frames), "--width", str(size[0]), "--height", str(size[1]), "--workers", "auto", "--timeline", str(timeline)]
    subprocess.run(["rm", "-rf", str(out)], check=True)
    t0 = time.time()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.time() - t0
    row = {"command": " ".join(cmd[1:]), "rc": done.returncode, "wall_s": round(wall, 2),
           "wall_fps": round(frames / wall, 1), "stderr_tail": done.stderr[-400:]}
    if done.returncode != 0 or not timeline.exists():
        return row
    by: dict[int, list[dict]] = defaultdict(list)
    for line in timeline.read_text().splitlines():
        e = json.loads(line)
        by[e["worker"]].append(e)
    start, first, period, counts = [], [], [], []
    for w, evs in by.items():
        if w < 0:
            continue
        evs.sort(key=lambda e: e["t"])
        at = {e["event"]: e["t"] for e in reversed(evs)}  # each event's first time
        written = [e["t"] for e in evs if e["event"] == "written"]
        counts.append(len(written))
        if "start" in at and "renderer" in at:
            start.append(at["renderer"] - t0)
        if written and "renderer" in at:
            first.append(written[0] - at["renderer"])
        period += [b - a for a, b in itertools.pairwise(written[3:])]

    def spread(v: list[float], scale: float = 1.0) -> list[float]:
        v = sorted(v)
        return [round(v[0] * scale, 2), round(statistics.median(v) * scale, 2), round(v[-1] * scale, 2)] if v else []

    row.update(processes=len(counts), frames_per_process=spread(counts), renderer_open_s=spread(start),
               first_frame_s=spread(first), steady_period_ms=spread(period, 1e3),
               steady_period_mean_ms=round(1e3 * statistics.fmean(period), 1) if period else None)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=40, help="frames of the one-process passes")
    ap.add_argument("--whole-frames", type=int, default=1200)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--size", default="1920x1080")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="frame-time-"))  # the frames written: not beside the results
    size = tuple(int(v) for v in a.size.split("x"))
    specs = {m: spec_file(m, tmp) for m in ("off", "on")}
    result: dict = {"cache_dir": os.environ.get("SEASYNTH_CACHE_DIR"), "one_process": {}, "whole": []}
    for mode in ("off", "on"):  # warm-up commands: fill the cache folder (columns, variants, texture sets)
        warm = whole(specs[mode], 96, size, tmp / "warm", tmp / "warm.jsonl")
        print("warm-up", mode, json.dumps(warm), flush=True)
    for mode in ("off", "on"):
        result["one_process"][mode] = one_process(mode, specs[mode], a.frames, size, a.out)
        print(mode, json.dumps(result["one_process"][mode]), flush=True)
    for pair in range(a.pairs):
        for mode in ("off", "on"):
            row = {"mode": mode, "pair": pair, **whole(specs[mode], a.whole_frames, size, tmp / "g", tmp / "t.jsonl")}
            print(json.dumps(row), flush=True)
            result["whole"].append(row)
    (a.out / "frame-time.json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
