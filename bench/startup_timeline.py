"""Where a local generate's start-up goes: a fresh `seasynth generate` (a new interpreter, the fork server, every
render process) with each render process noting its events (`--timeline`, seasynth.worker.local.pool.Timeline), summarised
per run:

    python -m seasynth.bench.startup_timeline SPEC OUT_DIR --resolution 1280x720 --workers 24 --frames 3000 [--rounds 2]

Per run: seconds from the command's start until the render processes had started (forked), opened their renderer
and written their first frame (min / median / max over processes), the first frames' stages (median ms), when 10,
50 and 100% of the frames were written, and frames over the command's wall time. OUT_DIR keeps each run's timeline
(JSON lines) and the summary (startup.json, startup.md).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

STAGES = ("sampling", "render", "formation", "ids", "labels", "encode")


def run_once(spec: Path, width: int, height: int, workers: int, frames: int, timeline: Path, gl: str) -> dict:
    timeline.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.time()
        subprocess.run([sys.executable, "-m", "seasynth.cli", "generate", str(spec), "--out", f"{tmp}/out",
                        "--width", str(width), "--height", str(height), "--frames", str(frames),
                        "--workers", str(workers), "--gl", gl, "--timeline", str(timeline)], check=True,
                       stdout=subprocess.DEVNULL)
        wall = time.time() - t0
    return summarise([json.loads(line) for line in timeline.read_text().splitlines()], t0, wall, frames)


def summarise(events: list[dict], t0: float, wall: float, frames: int) -> dict:
    per: dict[int, dict] = defaultdict(dict)
    stages: dict[tuple[int, str], list[float]] = defaultdict(list)  # (nth frame of its process, stage) -> ms
    written: list[float] = []
    by_worker: dict[int, list[dict]] = defaultdict(list)
    parent: dict[str, float] = {}
    for e in events:
        by_worker[e["worker"]].append(e)
    for w, evs in by_worker.items():
        prev, staged = None, []  # a process's events are sequential: each stage lasts from the event before it
        for e in sorted(evs, key=lambda e: e["t"]):
            t = e["t"] - t0
            if w < 0:  # the command itself: when it began and finished starting its render processes
                parent[e["event"]] = round(t, 2)
                continue
            if e["event"] in ("start", "renderer"):
                per[w][e["event"]] = t
            elif e["event"] == "written":
                written.append(t)
                per[w].setdefault("first_written", t)
            elif e["event"] in STAGES and prev is not None:
                if e["frame"] not in staged:
                    staged.append(e["frame"])
                stages[(staged.index(e["frame"]), e["event"])].append((t - prev) * 1e3)
            prev = t

    def spread(key: str) -> list[float]:
        vals = sorted(p[key] for p in per.values() if key in p)
        return [round(vals[0], 2), round(statistics.median(vals), 2), round(vals[-1], 2)] if vals else []

    written.sort()
    return {"frames": len(written), "wall_s": round(wall, 2), "wall_fps": round(frames / wall, 1),
            "processes": len(per), "pool_s": parent.get("pool"), "start_s": spread("start"), "renderer_s": spread("renderer"),
            "first_written_s": spread("first_written"),
            "stages_ms": {f"{n + 1}:{s}": round(statistics.median(v), 1) for (n, s), v in sorted(stages.items())},
            "done_at_s": {str(q): round(written[max(len(written) * q // 100 - 1, 0)], 2) for q in (10, 50, 100)}
            if written else {}}


def table(rows: list[dict]) -> str:
    head = ("| run | workers | resolution | wall fps | pool asked (s) | processes started (s) | renderers open (s) | first frame "
            "written (s) | 10% / 50% / 100% (s) |")
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['run']} | {r['workers']} | {r['resolution']} | {r['wall_fps']} | {r['pool_s']} | "
                     + " | ".join(" / ".join(str(x) for x in r[k]) for k in ("start_s", "renderer_s", "first_written_s"))
                     + " | " + " / ".join(str(v) for v in r["done_at_s"].values()) + " |")
    stage_keys = sorted({k for r in rows for k in r["stages_ms"]}, key=lambda k: (k.split(":")[0], STAGES.index(
        k.split(":")[1])))
    lines += ["", "Median ms of each stage of a process's first and second frame (1: first, 2: second):", "",
              "| run | " + " | ".join(stage_keys) + " |", "|---|" + "---|" * len(stage_keys)]
    for r in rows:
        lines.append(f"| {r['run']} | " + " | ".join(str(r["stages_ms"].get(k, "-")) for k in stage_keys) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("spec", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--resolution", action="append", default=None)
    ap.add_argument("--workers", type=int, action="append", default=None)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--gl", default="egl")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for rnd in range(a.rounds):
        for res in a.resolution or ["1280x720"]:
            w, h = (int(x) for x in res.split("x"))
            for workers in a.workers or [24]:
                name = f"{rnd + 1}-{res}-{workers}"
                row = {"run": name, "workers": workers, "resolution": res,
                       **run_once(a.spec, w, h, workers, a.frames, a.out / f"{name}.jsonl", a.gl)}
                print(json.dumps(row), flush=True)
                rows.append(row)
    (a.out / "startup.json").write_text(json.dumps(rows, indent=1))
    (a.out / "startup.md").write_text(table(rows) + "\n")
    print(table(rows))


if __name__ == "__main__":
    main()
