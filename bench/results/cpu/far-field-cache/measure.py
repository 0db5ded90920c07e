"""How often a render process builds the far field again, with far_field's per-process cache at 16 entries (0.11.0
before this change) and at 64: examples/urchins.yaml's scenes 0..N-1 sampled in order by one RenderSession (scene
sampling only, no GL), twice (the second pass a long run's later frames), counting the cache's misses, and the
seconds per frame of the sampling with each size, side by side in one run.

    SEASYNTH_CACHE_DIR=DIR python3 bench/results/cpu/far-field-cache/measure.py [N]
"""

import functools
import statistics
import sys
import time

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.scene import far_field as far
from seasynth.worker.scene import sample

frames = int(sys.argv[1]) if len(sys.argv) > 1 else 200
spec = load_spec("examples/urchins.yaml", {"frames": frames})
session = RenderSession()
terrains = {session.scene(spec, i).terrain.key for i in range(frames)}  # builds every terrain variant first
print(f"{frames} scenes, {len(terrains)} distinct terrains (style, variant and material)")
for size in (16, 64, 16, 64):
    cached = functools.lru_cache(maxsize=size)(far.far_field.__wrapped__)
    sample.far_field = cached
    times = []
    for i in list(range(frames)) * 2:
        t = time.perf_counter()
        session.scene(spec, i)
        times.append(time.perf_counter() - t)
    info = cached.cache_info()
    print(f"maxsize {size}: {info.misses} builds in {2 * frames} scenes ({info.misses / (2 * frames):.1%}), "
          f"{info.hits} hits; scene sampling mean {1e3 * statistics.fmean(times):.1f} ms, "
          f"second pass {1e3 * statistics.fmean(times[frames:]):.1f} ms")
some = sorted({session.scene(spec, i).terrain for i in range(frames)}, key=lambda t: t.key)[:8]
t = time.perf_counter()
for terrain in some:
    far.far_field.__wrapped__(terrain, float(spec.camera.clip[1]))
print(f"one far field: {1e3 * (time.perf_counter() - t) / 8:.1f} ms to build (mean of 8)")
