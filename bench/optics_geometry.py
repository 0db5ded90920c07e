"""What a port and a lens distortion cost on the CPU: the same frames with the camera geometry off and on, in one
process and one GL session, configurations interleaved frame by frame so drift hits all alike.

    python -m seasynth.bench.optics_geometry --out bench/results/cpu/optics-geometry [--frames 12] [--size 320x240]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from seasynth.bench.throughput import machine_description
from seasynth.service import __version__
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
CONFIGS: dict[str, dict] = {
    "off (pinhole)": {},
    "distortion": {"camera.distortion": [-0.2, 0.05, 0.001, -0.001, 0.0]},
    "flat port": {"camera.port": {"kind": "flat"}},
    "flat port + distortion": {"camera.port": {"kind": "flat"}, "camera.distortion": [-0.2, 0.05, 0.001, -0.001, 0.0]},
    "dome, pupil 10 mm behind centre": {"camera.port": {"kind": "dome", "pupil_offset_mm": [0.0, 0.0, -10.0]}},
}
OUTPUTS = {"outputs.labels": True, "outputs.meta": True, "outputs.depth": True, "outputs.instance": True}


def run(frames: int, width: int, height: int) -> dict:
    specs = {name: load_spec(EXAMPLE, {**OUTPUTS, **c, "camera.width": width, "camera.height": height,
                                       "frames": frames}) for name, c in CONFIGS.items()}
    times: dict[str, list[float]] = {name: [] for name in CONFIGS}
    cpu: dict[str, list[float]] = {name: [] for name in CONFIGS}
    renders: dict[str, list] = {}
    with RenderSession() as session:
        for name, spec in specs.items():  # warm-up: shaders and the rays' cache
            files = session.frame_files(spec, 0)
            meta = json.loads(files["meta/000000.json"])
            renders[name] = meta.get("optics", {}).get("geometry", {}).get("render")
        for i in range(frames):  # every frame's terrain and assets built and cached before any is timed
            session.frame_files(specs["off (pinhole)"], i)
        names = list(specs)
        for i in range(frames):
            for name in names[i % len(names):] + names[:i % len(names)]:  # each configuration first in turn
                spec = specs[name]
                t, c = time.perf_counter(), time.process_time()
                session.frame_files(spec, i)
                times[name].append(time.perf_counter() - t)
                cpu[name].append(time.process_time() - c)
        renderer = session.renderer_name
    base = statistics.median(cpu["off (pinhole)"])
    rows = [{"config": name, "cpu_ms_median": 1e3 * statistics.median(cpu[name]),
             "cpu_ratio_to_off": statistics.median(cpu[name]) / base,
             "wall_ms_median": 1e3 * statistics.median(ts), "wall_ms_min": 1e3 * min(ts),
             "render": None if renders[name] is None else f"{renders[name]['width']}x{renders[name]['height']}"}
            for name, ts in times.items()]
    return {"machine": machine_description(), "renderer": renderer, "code_version": __version__,
            "size": f"{width}x{height}", "frames": frames, "outputs": OUTPUTS, "rows": rows}


def markdown(r: dict) -> str:
    lines = [f"# What the port and lens geometry cost ({r['size']}, CPU)", "",
             f"Machine: {r['machine']}; {r['renderer']}; {r['code_version']}.", "",
             f"examples/urchins.yaml at {r['size']} with labels, meta, depth and instance on; {r['frames']} frames "
             "a configuration after a warm-up of each and of every frame's assets, configurations interleaved frame "
             "by frame (each first in turn) in one process "
             "(`python -m seasynth.bench.optics_geometry`). Whole frame_files calls (sampling, render, resample, "
             "labels, encode): this process's CPU time (all its threads, llvmpipe's included), which other "
             "processes on the machine disturb less than the wall time beside it.", "",
             "| configuration | wide render | CPU ms/frame median | vs off | wall ms median | wall min |",
             "|---|---|---|---|---|---|"]
    for row in r["rows"]:
        lines.append(f"| {row['config']} | {row['render'] or '-'} | {row['cpu_ms_median']:.0f} | "
                     f"{row['cpu_ratio_to_off']:.2f}x | {row['wall_ms_median']:.0f} | {row['wall_ms_min']:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--size", default="320x240")
    a = ap.parse_args()
    w, h = map(int, a.size.split("x"))
    result = run(a.frames, w, h)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "optics-geometry.json").write_text(json.dumps(result, indent=1) + "\n")
    (a.out / "optics-geometry.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
