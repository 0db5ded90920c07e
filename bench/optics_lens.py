"""What each lens and sensor effect costs on this machine: one frame's time with the effect on against off, side by
side in one run (same session, same frames, the example's default preset).

    python -m seasynth.bench.optics_lens --out bench/results/cpu/optics-lens [--width 320 --height 240 --frames 6]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession

EXAMPLE = "examples/urchins.yaml"
MOVING = {"camera.velocity_m_s": [0.5, 0.5], "camera.angular_rate_deg_s": [5.0, 5.0]}
CONFIGS: dict[str, dict] = {
    "off": {},
    "depth of field f/1.4, focus 0.5 m, 36 mm sensor": {"camera.aperture_f": 1.4, "camera.focus_m": 0.5,
                                                         "camera.sensor_width_mm": 36.0},
    "depth of field f/0.5, focus 0.3 m, 100 mm sensor": {"camera.aperture_f": 0.5, "camera.focus_m": 0.3,
                                                          "camera.sensor_width_mm": 100.0},
    "motion blur 1/60 s, 0.5 m/s, 5 deg/s": {"camera.exposure_s": 1 / 60, **MOVING},
    "rolling shutter 1/30 s readout, no blur": {"camera.readout_s": 1 / 30, **MOVING},
    "vignetting cos^4": {"camera.vignetting": 1.0},
    "sensor: photon + read noise, gain, auto exposure, gray world": {
        "noise.full_well_e": 5000.0, "noise.read_noise_e": 3.0, "noise.gain": 2.0, "noise.auto_exposure": 0.2,
        "noise.white_balance": "gray_world"},
    "gaussian_sigma 0.01 (before the sensor model)": {"noise.gaussian_sigma": 0.01},
}


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def measure(width: int, height: int, frames: int) -> dict:
    base = {"camera.width": width, "camera.height": height, "outputs.labels": True, "outputs.meta": True}
    specs = {name: load_spec(EXAMPLE, {**base, **extra}) for name, extra in CONFIGS.items()}
    times: dict[str, list[float]] = {name: [] for name in CONFIGS}
    instants: dict[str, list] = {name: [] for name in CONFIGS}
    coc: dict[str, list] = {name: [] for name in CONFIGS}
    with RenderSession() as session:
        for index in range(1, frames + 1):  # warm-up: every frame's assets and terrain cached, GL state set
            session.frame_files(specs["off"], index)
        for index in range(1, frames + 1):  # the configurations interleaved frame by frame
            session.frame_files(specs["off"], index)  # untimed: whatever changing frames costs is paid here
            for name, spec in specs.items():
                t = time.perf_counter()
                files = session.frame_files(spec, index)
                times[name].append(time.perf_counter() - t)
                optics = json.loads(files[f"meta/{index:06d}.json"]).get("optics") or {}
                instants[name].append((optics.get("motion_blur") or {}).get("instants"))
                coc[name].append((optics.get("depth_of_field") or {}).get("max_coc_radius_px"))
    rows = [{"config": name, "overrides": CONFIGS[name], "median_ms": 1000 * statistics.median(times[name]),
             "times_ms": [1000 * t for t in times[name]], "instants": instants[name], "max_coc_radius_px": coc[name]}
            for name in CONFIGS]
    off = rows[0]["median_ms"]
    for r in rows:
        r["ratio_to_off"] = r["median_ms"] / off
    return {"example": EXAMPLE, "width": width, "height": height, "frames": frames, "preset": "example's",
            "outputs": "image, labels, meta", "nproc": os.cpu_count(), "cpu": cpu_model(), "rows": rows}


def table(result: dict) -> str:
    lines = [f"# Lens and sensor effects: CPU cost at {result['width']}x{result['height']}", "",
             (f"`python -m seasynth.bench.optics_lens`: {result['example']}, frames 1-{result['frames']} per row, "
              f"outputs {result['outputs']}, one session, rows in one run. Machine: {result['nproc']} CPUs, "
              f"{result['cpu']}, Mesa llvmpipe."), "",
             ("| effect | median ms/frame | x off | motion instants per frame | largest circle of confusion, px radius "
              "(drawn at 16 at most) |"),
             "|---|---:|---:|---|---|"]
    for r in result["rows"]:
        inst = "" if all(i is None for i in r["instants"]) else ", ".join(str(i) for i in r["instants"])
        radii = [c for c in r["max_coc_radius_px"] if c is not None]
        coc = f"{min(radii):.1f}-{max(radii):.1f}" if radii else ""
        lines.append(f"| {r['config']} | {r['median_ms']:.1f} | {r['ratio_to_off']:.2f} | {inst} | {coc} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--frames", type=int, default=6)
    args = ap.parse_args()
    result = measure(args.width, args.height, args.frames)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "optics-lens.json").write_text(json.dumps(result, indent=1) + "\n")
    (args.out / "optics-lens.md").write_text(table(result))
    print(table(result))


if __name__ == "__main__":
    main()
