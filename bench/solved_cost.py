"""What the solved water column costs on this machine: a frame's render at the `default` preset with the column
(`worker.light.solved`) and without (today's closed form through K), side by side in one process, and the solve
itself, once per process and water.

    python -m seasynth.bench.solved_cost [--config NAME ...] [--repeats N] [--out DIR]

Each frame with the column builds its tables afresh (a new frame's SolvedWater, as every frame of a dataset does:
its view table at the camera's depth and its E_d table); the unit columns are solved once per process (the first
frame) and read from the process's cache after. Renders alternate on and off. Writes DIR/solved_cost.json and .md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

DEFAULT_CONFIGS = ("long-turbid-sun", "long-clear-sun", "ocean-sun-textured")


def measure(session, name: str, repeats: int) -> dict:
    from seasynth.bench.fidelity import FRAME, config_spec
    from seasynth.bench.fidelity_configs import WORLD_CONFIGS
    from seasynth.worker.frame.function import PRESETS
    from seasynth.worker.light.build import for_spec
    from seasynth.worker.light.solved import unit_column
    from seasynth.worker.render import Passes

    spec = config_spec(WORLD_CONFIGS[name])
    scene = session.scene(spec, FRAME)
    view = session.view(spec, scene)
    items = session.draw_items(scene)
    light = for_spec(scene.light, False)
    unit_column.cache_clear()
    t0 = time.perf_counter()
    for_spec(light, True).column.view_table(1.0)  # the solves, and one table
    solve_s = time.perf_counter() - t0

    def frame(on: bool) -> float:
        t = time.perf_counter()
        lt = for_spec(light, on)
        session.renderer.render(view, items, lt, None, PRESETS["default"], Passes())
        return time.perf_counter() - t

    frame(True), frame(False)  # programs compiled, meshes uploaded
    on, off = [], []
    for _ in range(repeats):
        on.append(frame(True))
        off.append(frame(False))
    return {"config": name, "solve_once_s": round(solve_s, 2), "ms_on": round(statistics.median(on) * 1e3, 1),
            "ms_off": round(statistics.median(off) * 1e3, 1),
            "ratio": round(statistics.median(on) / statistics.median(off), 3)}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", action="append")
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--out", type=Path, default=Path("bench/results/cpu/solved-column"))
    a = p.parse_args(argv)
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession

    with RenderSession() as session:
        rows = [measure(session, name, a.repeats) for name in a.config or DEFAULT_CONFIGS]
        renderer = session.renderer_name
    result = {"machine": machine_description(), "gl_renderer": renderer, "repeats": a.repeats, "rows": rows}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "solved_cost.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [f"The solved water column's cost, {result['machine']}, {renderer}: median of {a.repeats} renders of "
             "the configuration's frame at `default` (320x240), with the column (its tables built afresh each "
             "frame) and without, alternating; and the unit columns' solve, once per process and water.", "",
             "| config | frame ms, solved | frame ms, closed form | ratio | solve once, s |", "|---|---|---|---|---|"]
    lines += [f"| {r['config']} | {r['ms_on']} | {r['ms_off']} | {r['ratio']} | {r['solve_once_s']} |" for r in rows]
    (a.out / "solved_cost.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
