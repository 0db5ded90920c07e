"""What each optical effect costs: steady-state time per frame of a one-worker `generate` with each effect on, side by
side with the same spec with every effect off, in one run.

    python -m seasynth.bench.optics_cost [--spec FILE] [--width W] [--height H] [--frames N] [--rounds R]
                                         [--effects a,b] [--out DIR]

Each row switches one effect on at the spec's values in EFFECTS (typical settings, each documented in
docs/optics.md). Rows and the baseline run in R rounds, alternating order, and each keeps its fastest round (noise
only adds time). Writes DIR/optics_cost.json and .md.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

# One typical setting per effect: what a user turning it on would write.
EFFECTS: dict[str, dict] = {
    "marine snow": {"water.particles": {"enabled": True}},  # the water type's default density
    "forward scatter": {"water.forward_scatter": True},
    "flat port": {"camera.port": {"kind": "flat"}},
    "dome port": {"camera.port": {"kind": "dome", "pupil_offset_mm": [0.0, 0.0, 10.0]}},
    "lens distortion": {"camera.distortion": [-0.25, 0.08, 0.0, 0.0, 0.0]},
    "depth of field": {"camera.aperture_f": 1.4, "camera.focus_m": 2.0, "camera.sensor_width_mm": 36.0},
    "motion blur": {"camera.exposure_s": 1.0 / 60.0, "camera.velocity_m_s": [0.5, 1.0]},
    "vignetting": {"camera.vignetting": 1.0},
    "sensor": {"noise.full_well_e": 10000.0, "noise.read_noise_e": 5.0, "noise.auto_exposure": 0.4,
               "noise.white_balance": "gray_world"},
}


def run(spec_path: Path, *, width: int, height: int, frames: int, rounds: int, effects: list[str],
        out: Path | None, platform: str = "egl") -> dict:
    from seasynth.bench.throughput import machine_description, steady_generate, warm_caches, with_overrides
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import RenderSession

    base = load_spec(spec_path, {"camera.width": width, "camera.height": height, "frames": frames})
    with RenderSession(platform=platform) as session:
        renderer = session.renderer_name
        warm_caches(session, base, frames)
    rows = ["off", *effects]
    best: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(rounds):
            for k, name in enumerate(rows if round_ % 2 == 0 else rows[::-1]):
                spec = base if name == "off" else with_overrides(base, EFFECTS[name], frames)
                t = steady_generate(spec, Path(tmp) / f"{round_}-{k}")
                best[name] = min(t, best.get(name, t))
                print(json.dumps({"round": round_, "effect": name, "ms_per_frame": round(t * 1e3, 2)}), flush=True)
    result = {
        "machine": machine_description(), "gl_renderer": renderer, "spec": str(spec_path),
        "resolution": [width, height], "frames": frames, "rounds": rounds,
        "settings": {name: EFFECTS[name] for name in effects},
        "ms_per_frame": {name: round(best[name] * 1e3, 2) for name in rows},
        "ratio_to_off": {name: round(best[name] / best["off"], 3) for name in rows},
    }
    table = format_table(result)
    print(table)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "optics_cost.json").write_text(json.dumps(result, indent=1) + "\n")
        (out / "optics_cost.md").write_text(table + "\n")
    return result


def format_table(r: dict) -> str:
    lines = [f"# Optical effects' cost: {r['spec']} at {r['resolution'][0]}x{r['resolution'][1]}", "",
             f"machine: {r['machine']}  ", f"GL renderer: {r['gl_renderer']}  ",
             f"one-worker generate, {r['frames']} frames a row (steady state), fastest of {r['rounds']} rounds", "",
             "| effect | setting | ms per frame | x off |", "|---|---|---|---|"]
    for name, ms in r["ms_per_frame"].items():
        setting = "every effect off" if name == "off" else json.dumps(r["settings"][name], separators=(",", ":"))
        lines.append(f"| {name} | `{setting}` | {ms:.1f} | {r['ratio_to_off'][name]:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--spec", type=Path, default=Path("examples/urchins.yaml"))
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--effects", default=",".join(EFFECTS))
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    effects = [e for e in a.effects.split(",") if e]
    unknown = sorted(set(effects) - set(EFFECTS))
    if unknown:
        raise SystemExit(f"unknown effects {unknown}; known: {', '.join(EFFECTS)}")
    run(a.spec, width=a.width, height=a.height, frames=a.frames, rounds=a.rounds, effects=effects, out=a.out)


if __name__ == "__main__":
    main()
