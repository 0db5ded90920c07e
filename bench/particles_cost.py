"""Marine snow's cost: ms per frame with water.particles off and on (the water type's default density), paired
frame by frame in one process (each frame rendered off and on back to back, in alternating order), per example.

`python -m seasynth.bench.particles_cost [--size WxH] [--frames N] [--out DIR]`
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from seasynth.bench.throughput import machine_description, warm_caches, with_overrides
from seasynth.service.spec.dataset import load_spec

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SPECS = {"urchins (sun and sky)": EXAMPLES / "urchins.yaml", "night-dive (lamps)": EXAMPLES / "night-dive.yaml"}
SIDES = {"off": {}, "on": {"water.particles.enabled": True}}


def run(width: int, height: int, frames: int) -> dict:
    from seasynth.worker.frame.function import RenderSession

    rows = {}
    with RenderSession() as session:
        for name, path in SPECS.items():
            base = load_spec(path, {"camera.width": width, "camera.height": height})
            specs = {side: with_overrides(base, over, frames) for side, over in SIDES.items()}
            warm_caches(session, specs["off"], frames)
            for spec in specs.values():  # shaders and uploads
                session.frame_files(spec, 0)
            ms: dict[str, list[float]] = {side: [] for side in SIDES}
            counts = []
            for i in range(frames):
                for side in SIDES if i % 2 == 0 else reversed(SIDES):  # alternating order: drift hits both
                    t = time.perf_counter()
                    files = session.frame_files(specs[side], i)
                    ms[side].append((time.perf_counter() - t) * 1e3)
                    if side == "on":
                        counts.append(json.loads(files[f"meta/{i:06d}.json"])["optics"]["particles"]["count"])
            ratios = [b / a for a, b in zip(ms["off"], ms["on"])]
            rows[name] = {"off_ms": round(statistics.median(ms["off"]), 1), "on_ms": round(statistics.median(ms["on"]), 1),
                          "ratio_median": round(statistics.median(ratios), 3),
                          "ratio_quartiles": [round(q, 3) for q in statistics.quantiles(ratios, n=4)],
                          "frame_ms": {side: [round(t, 1) for t in v] for side, v in ms.items()},
                          "particles_median": int(statistics.median(counts)), "particles_max": max(counts)}
    return {"machine": machine_description(), "resolution": [width, height], "frames": frames, "rows": rows}


def table(result: dict) -> str:
    w, h = result["resolution"]
    lines = [f"# Marine snow's cost on the CPU ({w}x{h}, preset default)", "",
             (f"{result['machine']}; `frame_files` of {result['frames']} frames in one process, each frame off and "
              "on back to back (alternating which goes first), after a warm-up; medians of the frames' ms and of "
              "their on/off ratios (with the ratios' quartiles). Particles: the water type's default density "
              "(seasynth.service.water.MARINE_SNOW_PER_M3), diameters 0.5-5 mm."), "",
             "| spec | off (ms) | on (ms) | on/off (quartiles) | particles per frame (median, max) |",
             "|---|---|---|---|---|"]
    for name, r in result["rows"].items():
        q = r["ratio_quartiles"]
        lines.append(f"| {name} | {r['off_ms']} | {r['on_ms']} | {r['ratio_median']} ({q[0]}-{q[2]}) | "
                     f"{r['particles_median']}, {r['particles_max']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    result = run(width, height, args.frames)
    print(table(result))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "particles.json").write_text(json.dumps(result, indent=1) + "\n")
        (args.out / "particles.md").write_text(table(result))


if __name__ == "__main__":
    main()
