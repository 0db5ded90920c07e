"""Open water against the path tracer: the radiance of water with nothing in view, looking from 50 degrees up to 50
degrees down, for every Jerlov type at three depths (sun and sky; no seabed, no objects), from the physical model's
float64 twin (`worker.light.volume.volume`, what the resolve shader computes) and from Mitsuba's volumetric path
tracer of the same water. It shows where the model's view-ray scattering disagrees with physics as a function of
water, depth and elevation, which a frame's mix of seabed and water hides.

    python -m seasynth.bench.open_water [--spp N] [--out DIR] [--waters I,II,...] [--depths 5,12,25]

Each column of the 8 x 48 image is one azimuth (the camera looks along +y, the sun at the fidelity bench's 60
degrees elevation, azimuth 30); rows are elevations. Writes DIR/open_water.json and .md: per water and depth the
mean radiance of each elevation band, the model's ratio to the path tracer, and the 8-bit sRGB RMS difference.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import numpy as np

WIDTH, HEIGHT = 8, 48
INTRINSICS = {"fx": 20.0, "fy": 20.0, "cx": 3.5, "cy": 23.5}  # 45 degrees either side of level, 22 across
BANDS = ((20.0, 50.0), (5.0, 20.0), (-5.0, 5.0), (-20.0, -5.0), (-50.0, -20.0))  # elevation bands, degrees
VIEW = {"workspaces.camera": {"min": [0.0, -1.7, 1.2], "max": [0.0, -1.7, 1.2]},
        "workspaces.look_at": {"min": [0.0, -1.2, 1.2], "max": [0.0, -1.2, 1.2]},
        "camera.look_at_jitter_m": 0.0, "camera.intrinsics": INTRINSICS}


def open_water_spec(water: str, depth_m: float):
    from seasynth.bench.fidelity import config_spec
    from seasynth.service.spec.dataset import DatasetSpec, apply_overrides

    spec = config_spec(f"{water}:sun@{depth_m:g}", (WIDTH, HEIGHT))
    d = spec.model_dump(mode="json", exclude_none=True)
    d["camera"].pop("hfov_deg", None)
    return DatasetSpec.model_validate(apply_overrides(d, VIEW))


def measure(session, water: str, depth_m: float, spp: int) -> dict:
    from seasynth.bench.fidelity import FRAME
    from seasynth.bench.fidelity_scene import path_traced_scene
    from seasynth.bench.pathtracer import render
    from seasynth.worker.frame.srgb import encode_srgb8
    from seasynth.worker.light.volume import camera_depth, pixel_rays, volume

    spec = open_water_spec(water, depth_m)
    scene = session.scene(spec, FRAME)
    view = session.view(spec, scene)
    pts = dataclasses.replace(path_traced_scene(session, spec), meshes=())
    pt = render(pts, spp, seed=1).astype(np.float64)
    dirs_world, dirs_cam = pixel_rays(view.K, WIDTH, HEIGHT, scene.world_from_cam)
    light = scene.light
    model = volume(np.zeros((HEIGHT, WIDTH, 3)), np.full((HEIGHT, WIDTH), np.inf), dirs_world, dirs_cam,
                   camera_depth(light, scene.world_from_cam), light)
    elevation = np.degrees(np.arcsin(np.clip(dirs_world[..., 2], -1.0, 1.0)))
    bands = []
    for lo, hi in BANDS:
        m = (elevation >= lo) & (elevation < hi)
        p, q = pt[m].mean(axis=0), model[m].mean(axis=0)
        bands.append({"elevation_deg": [lo, hi], "path_tracer": p.round(6).tolist(), "model": q.round(6).tolist(),
                      "ratio": np.where(p > 1e-6, q / np.maximum(p, 1e-12), np.nan).round(3).tolist()})
    rms8 = float(np.sqrt(np.mean((encode_srgb8(model).astype(float) - encode_srgb8(pt).astype(float)) ** 2)))
    m = light.medium
    return {"water": water, "depth_m": depth_m, "a": m.a.tolist(), "b": m.b.tolist(), "g": m.g, "K": m.k.tolist(),
            "spp": spp, "rms_8bit": round(rms8, 2), "bands": bands}


def table(rows: list[dict]) -> str:
    head = ("| water | depth m | 8-bit RMS | " + " | ".join(f"{lo:+g}..{hi:+g} deg (G, B)" for lo, hi in BANDS)
            + " |\n|---|---|---|" + "---|" * len(BANDS))
    lines = [head]
    for r in rows:
        cells = [f"{b['ratio'][1]:.2f}, {b['ratio'][2]:.2f}" for b in r["bands"]]
        lines.append(f"| {r['water']} | {r['depth_m']:g} | {r['rms_8bit']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--spp", type=int, default=8192)
    p.add_argument("--out", type=Path, default=Path("bench/results/cpu/open-water"))
    p.add_argument("--waters", default="I,II,III,1C,3C,5C,7C,9C")
    p.add_argument("--depths", default="5,12,25")
    a = p.parse_args(argv)
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession

    rows = []
    with RenderSession() as session:
        for water in a.waters.split(","):
            for depth in (float(x) for x in a.depths.split(",")):
                rows.append(measure(session, water, depth, a.spp))
                print(json.dumps({k: rows[-1][k] for k in ("water", "depth_m", "rms_8bit")}), flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    result = {"machine": machine_description(), "size": [WIDTH, HEIGHT], "spp": a.spp, "rows": rows}
    (a.out / "open_water.json").write_text(json.dumps(result, indent=1) + "\n")
    (a.out / "open_water.md").write_text(
        f"Open water, the physical model's twin over Mitsuba's path tracer ({a.spp} spp, {WIDTH}x{HEIGHT}, "
        f"{result['machine']}): the model's mean radiance over the path tracer's in each elevation band, green and "
        "blue (red is nearly absorbed), and the 8-bit sRGB RMS difference of the whole image.\n\n"
        + table(rows) + "\n")
    print(table(rows))
    if not math.isfinite(sum(r["rms_8bit"] for r in rows)):
        raise SystemExit("a row has no finite RMS")


if __name__ == "__main__":
    main()
