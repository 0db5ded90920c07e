"""False horizons: frames of a spec whose rays point down to where the water would still show a seabed
(exp(-K t) > 1/255, t the distance to z = 0 within the far clip, K the frame's own attenuation) yet end in open
water, with the far field off and on. `python -m seasynth.bench.horizon [SPEC] [--frames N] [--size WxH] [--out DIR]`
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS, RenderSession, scene_light
from seasynth.worker.render import Passes

VISIBLE = 1.0 / 255.0


def ray_directions(view, world_from_cam: np.ndarray) -> np.ndarray:
    """(h, w, 3) unit world directions through the pixel centres (integer image coordinates, as K has them)."""
    u, v = np.meshgrid(np.arange(view.width, dtype=np.float64), np.arange(view.height, dtype=np.float64))
    cam = np.stack([(u - view.K[0, 2]) / view.K[0, 0], (v - view.K[1, 2]) / view.K[1, 1], np.ones_like(u)], -1)
    world = cam @ world_from_cam[:3, :3].T
    return world / np.linalg.norm(world, axis=-1, keepdims=True)


def count(session, spec) -> dict:
    frames = pixels = 0
    for i in range(spec.frames):
        scene = session.scene(spec, i)
        view = session.view(spec, scene)
        result = session.renderer.render(view, session.draw_items(scene), scene_light(scene), scene.water,
                                         PRESETS[spec.quality], Passes(range=True))
        w = ray_directions(view, scene.world_from_cam)
        K = float(np.min(scene.light.medium.k if scene.light is not None else scene.water.beta_D))
        with np.errstate(divide="ignore"):
            t = np.where(w[..., 2] < 0, scene.world_from_cam[2, 3] / -w[..., 2], np.inf)
        false_horizon = (t < view.far) & (np.exp(-K * t) > VISIBLE) & ~np.isfinite(result.range_m)
        frames += bool(false_horizon.any())
        pixels += int(false_horizon.sum())
    total = spec.frames * spec.camera.width * spec.camera.height
    return {"frames": frames, "pixels": pixels, "pixel_share": round(pixels / total, 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("spec", nargs="?", default="examples/urchins.yaml")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--out", type=Path, default=Path("bench/results/cpu/horizon"))
    a = parser.parse_args()
    width, height = (int(x) for x in a.size.split("x"))
    rows = {}
    with RenderSession() as session:
        for on in (False, True):
            spec = load_spec(a.spec, {"frames": a.frames, "camera.width": width, "camera.height": height,
                                      "terrain.far_field": on})
            rows["on" if on else "off"] = count(session, spec)
        renderer = session.renderer_name
    result = {"spec": a.spec, "frames": a.frames, "size": [width, height], "renderer": renderer, "rows": rows}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "horizon.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = ["| terrain.far_field | frames with a false horizon | pixels | share of all pixels |", "|---|---|---|---|"]
    lines += [f"| {k} | {r['frames']} of {a.frames} | {r['pixels']} | {100 * r['pixel_share']:.2f}% |"
              for k, r in rows.items()]
    (a.out / "horizon.md").write_text(f"{a.spec}, {a.frames} frames at {width}x{height}, {renderer}\n\n"
                                      + "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
