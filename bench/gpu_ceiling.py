"""The GPU's ceiling: P processes each rendering (no labels, no encoding, no writing) the same four frames of
examples/urchins.yaml in a loop for 8 s; prints the frames/s of all of them together.

    python -m seasynth.bench.gpu_ceiling WIDTHxHEIGHT VARIANT@PROCS[@DEPTH] ...

DEPTH (default 1): frames each process keeps in flight; above 1, frame k+1's passes are queued before frame k's
reads are fetched (GLRenderer.queue and fetch, as seasynth.bench.gpu_timeline uses them), so the GPU never waits for it.
VARIANT: default (the default preset, ids pass, 8-bit codes), fragment (the same with the fragment resolve),
no-ids, draft, no-sun-shadow, no-scatter (sun and sky scattering off). Results: bench/results/gpu/passes.md.
"""
import collections
import dataclasses
import multiprocessing as mp
import sys
import time

VARIANTS = ("default", "fragment", "no-ids", "draft", "no-sun-shadow", "no-scatter")


def worker(variant, seconds, barrier, q, res, depth=1):
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import PRESETS, RenderSession, scene_light
    from seasynth.worker.render import Passes
    w, h = res
    spec = load_spec("examples/urchins.yaml", {"camera.width": w, "camera.height": h})
    with RenderSession() as s:
        frames = []
        for i in range(4):
            scene = s.scene(spec, i)
            light = scene_light(scene)
            if variant == "no-sun-shadow" and hasattr(light, "terms"):
                light = dataclasses.replace(light, terms=dataclasses.replace(light.terms, sun_shadows=False))
            if variant == "no-scatter" and hasattr(light, "terms"):
                light = dataclasses.replace(light, terms=dataclasses.replace(light.terms, scattering=False, sky=False))
            frames.append((s.view(spec, scene), s.draw_items(scene), light, scene.water))
        if variant == "fragment":
            s.renderer.compute_resolve = False
        preset = PRESETS["draft" if variant == "draft" else "default"]
        passes = Passes(ids=variant != "no-ids", srgb8=True)
        for v, it, lt, wt in frames:
            s.renderer.render(v, it, lt, wt, preset, passes)
        barrier.wait()
        t0, n = time.perf_counter(), 0
        inflight = collections.deque()
        while time.perf_counter() - t0 < seconds:
            v, it, lt, wt = frames[n % 4]
            if depth == 1:
                s.renderer.render(v, it, lt, wt, preset, passes)
            else:
                inflight.append(s.renderer.queue(v, it, lt, wt, preset, passes))
                if len(inflight) == depth:
                    s.renderer.fetch(inflight.popleft())
            n += 1
        while inflight:
            s.renderer.fetch(inflight.popleft())
        q.put(n)


if __name__ == "__main__":
    ctx = mp.get_context("spawn")
    res = tuple(int(x) for x in sys.argv[1].split("x"))
    for spec in sys.argv[2:]:
        variant, procs, *rest = spec.split("@")
        if variant not in VARIANTS:  # an unknown name would otherwise render the default variant under its label
            raise SystemExit(f"variant {variant!r}: one of {', '.join(VARIANTS)}")
        procs, depth, seconds = int(procs), int(rest[0]) if rest else 1, 8.0
        barrier, q = ctx.Barrier(procs), ctx.Queue()
        ps = [ctx.Process(target=worker, args=(variant, seconds, barrier, q, res, depth)) for _ in range(procs)]
        for p in ps:
            p.start()
        total = sum(q.get() for _ in ps)
        for p in ps:
            p.join()
        print(f"{res[0]}x{res[1]} {variant:14s} procs={procs:3d} depth={depth} render-only fps={total / seconds:7.1f}",
              flush=True)
