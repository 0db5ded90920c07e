"""What the forward-scatter blur (water.forward_scatter) costs on this machine: whole frames of one spec with it off
and on, interleaved frame by frame in one run, and the blur alone on the same frames' buffers.

    python -m seasynth.bench.forward_scatter_cost OUT [--spec examples/urchins.yaml] [--frames 20] [--size 320x240]
        [--jerlov 1C ...]

Writes OUT/forward_scatter_cost.json and .md: per water type, the median ms per frame off, on, their ratio and the
median ms of `forward_scatter` itself (the frame's float buffers, clean image and range, in memory). Every frame is
rendered once before the timing, so neither side pays for filling the caches.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from seasynth.service.spec.dataset import load_spec

WARMUP = 3  # frame indices not timed: uploads, shader compiles


def timed_ms(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return (time.perf_counter() - t0) * 1e3


def blur_alone_ms(session, spec, index: int) -> float:
    """ms of forward_scatter on frame `index`'s buffers (rendered once, outside the timing)."""
    from seasynth.worker.frame.function import PRESETS
    from seasynth.worker.optics.forward_scatter import forward_scatter
    from seasynth.worker.render import Passes

    scene = session.scene(spec, index)
    view = session.view(spec, scene)
    res = session.renderer.render(view, session.draw_items(scene), scene.light, scene.water, PRESETS[spec.quality],
                                  Passes(clean=True, range=True))
    return timed_ms(forward_scatter, res.image, res.clean, res.range_m, scene.light.medium, view.K[0, 0], view.K[1, 1])


def run(out: Path, spec_path: Path, frames: int, size: tuple[int, int], waters: list[str]) -> dict:
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession

    rows = []
    with RenderSession() as session:
        for jerlov in waters:
            base = {"camera.width": size[0], "camera.height": size[1], "water.model": "physical",
                    "water.jerlov": [jerlov], "frames": WARMUP + frames}
            off = load_spec(spec_path, base)
            on = load_spec(spec_path, {**base, "water.forward_scatter": True})
            times: dict[str, list[float]] = {"off": [], "on": [], "blur": []}
            for index in range(WARMUP + frames):  # every frame's terrain and assets into the caches first
                session.frame_files(off, index)
            for index in range(WARMUP + frames):
                first, second = (off, on) if index % 2 == 0 else (on, off)  # neither always runs first
                t_first = timed_ms(session.frame_files, first, index)
                t_second = timed_ms(session.frame_files, second, index)
                t_off, t_on = (t_first, t_second) if first is off else (t_second, t_first)
                t_blur = blur_alone_ms(session, on, index)
                if index >= WARMUP:
                    for key, t in (("off", t_off), ("on", t_on), ("blur", t_blur)):
                        times[key].append(t)
            med = {k: statistics.median(v) for k, v in times.items()}
            rows.append({"jerlov": jerlov, "frames": frames, "off_ms": round(med["off"], 1),
                         "on_ms": round(med["on"], 1), "ratio": round(med["on"] / med["off"], 3),
                         "blur_ms": round(med["blur"], 1)})
            print(json.dumps(rows[-1]), flush=True)
        result = {"machine": machine_description(), "gl_renderer": session.renderer_name, "spec": str(spec_path),
                  "size": list(size), "warmup": WARMUP, "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "forward_scatter_cost.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [f"# Forward-scatter blur: CPU cost ({size[0]}x{size[1]}, {spec_path})", "",
             f"machine: {result['machine']}  ", f"GL renderer: {result['gl_renderer']}  ",
             (f"median ms per frame (all of the spec's outputs) over {frames} frame indices after {WARMUP} warm-up "
              "ones, every index rendered once before timing (caches filled), off and on interleaved frame by frame "
              "(alternating which goes first); blur: `forward_scatter` alone on the frame's buffers"), "",
             "| water | off ms | on ms | on / off | blur ms |", "|---|---|---|---|---|",
             *(f"| Jerlov {r['jerlov']} | {r['off_ms']} | {r['on_ms']} | {r['ratio']} | {r['blur_ms']} |"
               for r in rows)]
    (out / "forward_scatter_cost.md").write_text("\n".join(lines) + "\n")
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path)
    p.add_argument("--spec", type=Path, default=Path("examples/urchins.yaml"))
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--size", default="320x240")
    p.add_argument("--jerlov", action="append")
    a = p.parse_args()
    w, h = (int(v) for v in a.size.split("x"))
    run(a.out, a.spec, a.frames, (w, h), a.jerlov or ["1C", "3C"])


if __name__ == "__main__":
    main()
