"""One checkout's side of a side-by-side fidelity comparison: the fidelity bench's scenes (stored references)
rendered with chosen presets, scored as the bench scores them, in one process; run it from two checkouts in turn.

    python -m seasynth.bench.fidelity_side CONFIG[,CONFIG...] [PRESET[,PRESET...]]

Prints per configuration and preset: PSNR (8-bit sRGB) against the reference, ms per frame (median of 6 renders
after one warm-up), the path tracer's samples per pixel at equal error and their ratio to the ms.
"""
from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

from seasynth.bench.accuracy import psnr_db
from seasynth.bench.fidelity import (
    CONFIGS,
    FRAME,
    config_spec,
    equal_error_spp,
    mse,
    stored_reference,
)
from seasynth.bench.fidelity_scene import path_traced_scene

REFERENCES = Path(__file__).resolve().parent / "results" / "cpu" / "fidelity-references"


def main(names: list[str], presets: list[str]) -> None:
    from seasynth.worker.frame.function import PRESETS, RenderSession
    from seasynth.worker.frame.srgb import encode_srgb8
    from seasynth.worker.render import Passes

    with RenderSession() as s:
        for name in names:
            spec = config_spec(CONFIGS[name])
            scene = s.scene(spec, FRAME)
            view, items = s.view(spec, scene), s.draw_items(scene)
            ref = stored_reference(REFERENCES, name, path_traced_scene(s, spec))
            halves8 = [encode_srgb8(h) for h in ref.halves]
            target = encode_srgb8(ref.mean)
            for p in presets:
                times = []
                for _ in range(7):
                    t0 = time.perf_counter()
                    res = s.renderer.render(view, items, scene.light, None, PRESETS[p], Passes())
                    times.append((time.perf_counter() - t0) * 1e3)
                ms = statistics.median(times[1:])
                image = encode_srgb8(res.image)
                spp = equal_error_spp(mse(image, target), mse(*halves8), ref.spp)
                print(f"{name:14s} {p:8s} psnr {psnr_db(image, target):6.2f} ms {ms:6.1f} eq_spp {spp:9.0f} "
                      f"spp/ms {spp / ms:8.1f}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    main(sys.argv[1].split(","), (sys.argv[2] if len(sys.argv) > 2 else "draft,default").split(","))
