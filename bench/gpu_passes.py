"""GPU time of each pass of a frame (GL_TIME_ELAPSED queries around the shadow maps, the surface pass, the
resolve and the ids pass), one process, six frames of examples/urchins.yaml, per preset: medians in ms.

    python -m seasynth.bench.gpu_passes WIDTHxHEIGHT

Results: bench/results/gpu/passes.md.
"""
import collections
import statistics
import sys

import seasynth.worker.render.gl_light as gl_light
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS, RenderSession, scene_light
from seasynth.worker.render import Passes


def main(w: int, h: int) -> None:
    spec = load_spec("examples/urchins.yaml", {"camera.width": w, "camera.height": h})
    with RenderSession() as s:
        r = s.renderer; GL = r.gl
        times = collections.defaultdict(list)
        pending = []
        def timed(name, fn):
            def run(*a, **k):
                q = GL.glGenQueries(1)[0]
                GL.glBeginQuery(GL.GL_TIME_ELAPSED, q)
                out = fn(*a, **k)
                GL.glEndQuery(GL.GL_TIME_ELAPSED)
                pending.append((name, q))
                return out
            return run
        draw = r._draw
        r._draw = lambda view, items, locs, *, lit, ids: timed("surface" if lit else ("ids" if ids else "coverage-or-ids"), draw)(view, items, locs, lit=lit, ids=ids)
        gl_light._draw_depth = timed("shadow-map", gl_light._draw_depth)
        real_arrays = GL.glDrawArrays
        GL.glDrawArrays = timed("resolve", real_arrays)
        GL.glDispatchCompute = timed("resolve", GL.glDispatchCompute)
        print("compute_resolve", r.compute_resolve)
        frames = []
        for i in range(6):
            scene = s.scene(spec, i)
            frames.append((s.view(spec, scene), s.draw_items(scene), scene_light(scene), scene.water, scene.light.terms if scene.light else None))
        for preset in ("default", "fast", "draft"):
            times.clear()
            for rep in range(3):
                for v, it, lt, wt, terms in frames:
                    pending.clear()
                    s.renderer.render(v, it, lt, wt, PRESETS[preset], Passes(ids=True, srgb8=True))
                    per = collections.Counter()
                    for name, q in pending:
                        per[name] += GL.glGetQueryObjectuiv(q, GL.GL_QUERY_RESULT) / 1e6
                        GL.glDeleteQueries(1, [q])
                    if rep:
                        for k, vv in per.items(): times[k].append(vv)
            print(preset, {k: round(statistics.median(v), 3) for k, v in times.items()}, "sum", round(sum(statistics.median(v) for v in times.values()), 3), flush=True)
        print("terms", [f[4] for f in frames])


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m seasynth.bench.gpu_passes WIDTHxHEIGHT")
    main(*(int(x) for x in sys.argv[1].split("x")))
