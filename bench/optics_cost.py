"""What each optical effect costs: per frame, the whole frame's time with one effect on beside the same spec with every
effect off, and the effect's own CPU time (its prepare, expose and develop, less the renders it asks for), in one run.

    python -m seasynth.bench.optics_cost [--spec FILE] [--width W] [--height H] [--frames N] [--rounds R]
                                         [--effects a,b] [--out DIR]

Each row switches one effect on at the spec's values in EFFECTS (typical settings, each documented in
docs/optics.md). One process and one GL session render frames 1..N of every row after a warm-up (frame 0 of each row:
shaders, uploads, the port's rays; every frame's terrain and assets built), in R rounds that alternate the rows'
order, so drift on a shared machine hits every row alike. Each row keeps its fastest round's medians (noise only adds
time). Frame times are wall and process CPU time (all threads, the software rasteriser's included); an effect's own
time is CPU time inside its methods less the renders inside them (motion blur's extra instants are render time).
Writes DIR/optics_cost.json and .md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

MOVING = {"camera.velocity_m_s": [0.5, 1.0]}
# One typical setting per effect: what a user turning it on would write.
EFFECTS: dict[str, dict] = {
    "marine snow": {"water.particles": {"enabled": True}},  # the water type's default density
    "forward scatter": {"water.forward_scatter": True},
    "flat port": {"camera.port": {"kind": "flat"}},
    "dome port": {"camera.port": {"kind": "dome", "pupil_offset_mm": [0.0, 0.0, 10.0]}},
    "lens distortion": {"camera.distortion": [-0.25, 0.08, 0.0, 0.0, 0.0]},
    "flat port + distortion": {"camera.port": {"kind": "flat"}, "camera.distortion": [-0.2, 0.05, 0.001, -0.001, 0.0]},
    "depth of field": {"camera.aperture_f": 1.4, "camera.focus_m": 2.0, "camera.sensor_width_mm": 36.0},
    "depth of field at the cap": {"camera.aperture_f": 0.5, "camera.focus_m": 0.3, "camera.sensor_width_mm": 100.0},
    "motion blur": {"camera.exposure_s": 1.0 / 60.0, **MOVING},
    "rolling shutter": {"camera.readout_s": 1.0 / 30.0, **MOVING},
    "vignetting": {"camera.vignetting": 1.0},
    "sensor": {"noise.full_well_e": 10000.0, "noise.read_noise_e": 5.0, "noise.auto_exposure": 0.4,
               "noise.white_balance": "gray_world"},
}
OUTPUTS = {"outputs.labels": True, "outputs.meta": True}


def detail(record: dict) -> str:
    """What an effect did to one frame, from meta's optics record."""
    parts = []
    if "particles" in record:
        parts.append(f"{record['particles']['count']} particles")
    if "forward_scatter" in record:
        parts.append(f"{len(record['forward_scatter']['levels_px'])} blur levels")
    if "geometry" in record:
        g = record["geometry"]["render"]
        parts.append(f"wide render {g['width']}x{g['height']}")
    if "depth_of_field" in record:
        parts.append(f"largest CoC {record['depth_of_field']['max_coc_radius_px']:.1f} px")
    if "motion_blur" in record:
        parts.append(f"{record['motion_blur']['instants']} instants")
    return ", ".join(parts)


class Stopwatch:
    """CPU seconds inside the effects' prepare, expose and develop (less the renders they ask for) and in renders."""

    def __init__(self, session) -> None:
        self.render_s = 0.0
        self.effect_s = 0.0
        render = session.renderer.render

        def timed_render(*args, **kwargs):
            c = time.process_time()
            try:
                return render(*args, **kwargs)
            finally:
                self.render_s += time.process_time() - c

        session.renderer.render = timed_render

    def effects(self, make):
        """`make` (seasynth.worker.optics.effects) with every effect's methods timed."""

        def timed():
            out = make()
            for effect in out:
                for method in ("prepare", "expose", "develop"):
                    setattr(effect, method, self._timed(getattr(effect, method)))
            return out

        return timed

    def _timed(self, fn):
        def call(*args):
            c, r = time.process_time(), self.render_s
            try:
                return fn(*args)
            finally:
                self.effect_s += (time.process_time() - c) - (self.render_s - r)

        return call


def run(spec_path: Path, *, width: int, height: int, frames: int, rounds: int, effects: list[str],
        out: Path | None, platform: str = "egl") -> dict:
    from seasynth.bench.throughput import machine_description, warm_caches, with_overrides
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker import optics
    from seasynth.worker.frame.function import RenderSession

    base = load_spec(spec_path, {"camera.width": width, "camera.height": height, "frames": frames + 1, **OUTPUTS})
    rows = ["off", *effects]
    specs = {name: base if name == "off" else with_overrides(base, EFFECTS[name], frames + 1) for name in rows}
    best: dict[str, dict] = {}
    details: dict[str, str] = {}
    make = optics.effects
    with RenderSession(platform=platform) as session:
        renderer = session.renderer_name
        warm_caches(session, base, frames + 1)
        watch = Stopwatch(session)
        optics.effects = watch.effects(make)
        try:
            for name in rows:  # shaders, uploads, the rays' caches
                session.frame_files(specs[name], 0)
            for round_ in range(rounds):
                for name in rows if round_ % 2 == 0 else rows[::-1]:
                    got = time_row(session, watch, specs[name], frames)
                    details[name] = got.pop("detail")
                    best[name] = {k: min(v, best.get(name, got)[k]) for k, v in got.items()}
                    print(json.dumps({"round": round_, "effect": name, **got}), flush=True)
        finally:
            optics.effects = make
    off = best["off"]
    result = {
        "machine": machine_description(), "gl_renderer": renderer, "spec": str(spec_path),
        "resolution": [width, height], "frames": frames, "rounds": rounds, "outputs": OUTPUTS,
        "settings": {name: EFFECTS[name] for name in effects},
        "rows": {name: {**best[name], "ratio_to_off": round(best[name]["cpu_ms"] / off["cpu_ms"], 3),
                        "detail": details[name]} for name in rows},
    }
    table = format_table(result)
    print(table)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "optics_cost.json").write_text(json.dumps(result, indent=1) + "\n")
        (out / "optics_cost.md").write_text(table + "\n")
    return result


def time_row(session, watch: Stopwatch, spec, frames: int) -> dict:
    """Medians over frames 1..frames of one spec: wall and CPU ms a frame, and the effects' own CPU ms."""
    wall, cpu, own = [], [], []
    record: dict = {}
    for index in range(1, frames + 1):
        e, t, c = watch.effect_s, time.perf_counter(), time.process_time()
        files = session.frame_files(spec, index)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        own.append(watch.effect_s - e)
        record = json.loads(files[f"meta/{index:06d}.json"]).get("optics") or {}

    def ms(v: list[float]) -> float:
        return round(1e3 * statistics.median(v), 1)

    return {"wall_ms": ms(wall), "cpu_ms": ms(cpu), "effect_cpu_ms": ms(own), "detail": detail(record)}


def format_table(r: dict) -> str:
    lines = [f"# Optical effects' cost: {r['spec']} at {r['resolution'][0]}x{r['resolution'][1]}", "",
             f"machine: {r['machine']}  ", f"GL renderer: {r['gl_renderer']}  ",
             (f"`frame_files` of frames 1-{r['frames']} a row (labels and meta on) in one process, after a warm-up; "
              f"{r['rounds']} rounds alternating the rows' order, each row's fastest round of medians. CPU: the "
              "process's CPU time (all threads); effect: CPU time inside the effects less their renders."), "",
             "| effect | setting | wall ms | CPU ms | x off (CPU) | effect CPU ms | what it did (last frame) |",
             "|---|---|---|---|---|---|---|"]
    for name, row in r["rows"].items():
        setting = "every effect off" if name == "off" else json.dumps(r["settings"][name], separators=(",", ":"))
        lines.append(f"| {name} | `{setting}` | {row['wall_ms']:.1f} | {row['cpu_ms']:.1f} | "
                     f"{row['ratio_to_off']:.3f} | {row['effect_cpu_ms']:.1f} | {row['detail']} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--spec", type=Path, default=Path("examples/urchins.yaml"))
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--frames", type=int, default=4)
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
