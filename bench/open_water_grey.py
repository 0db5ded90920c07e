"""Open water, one channel at a time: the path tracer rendered with every RGB channel given one channel's a and b (a
grey medium), against the same tracer's RGB render and the solved water column (`worker.light.column`, capped at the
tracer's 63 scatterings). It tells whether the RGB render's band means hold for each channel on its own: Mitsuba's RGB
volumetric path tracer shares its free paths between channels whose attenuation differs up to 13x in clear water.

    python -m seasynth.bench.open_water_grey [--spp N] [--photons N] [--cases I:5,I:25,...] [--out DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--spp", type=int, default=16384)
    p.add_argument("--photons", type=int, default=80000)
    p.add_argument("--cases", default="I:5,I:12,I:25,III:5,III:12")
    p.add_argument("--out", type=Path, default=Path("bench/results/cpu/open-water-column"))
    a = p.parse_args(argv)
    from seasynth.bench.fidelity_scene import path_traced_scene
    from seasynth.bench.open_water import BANDS, open_water_spec
    from seasynth.bench.open_water_column import PT_MAX_SCATTERINGS, radiance, solve_water, views
    from seasynth.bench.pathtracer import render
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession

    rows = []
    with RenderSession() as session:
        for case in a.cases.split(","):
            water, depth = case.split(":")
            light, cam_depth, dirs, elevation = views(session, water, float(depth))
            pts = dataclasses.replace(path_traced_scene(session, open_water_spec(water, float(depth))), meshes=())
            rgb = render(pts, a.spp, seed=1).astype(np.float64)
            cols = solve_water(light, cam_depth, a.photons, PT_MAX_SCATTERINGS, seed=1)
            solved = radiance(cols, light, cam_depth, dirs)
            row = {"water": water, "depth_m": float(depth), "channels": {}}
            for ch, name in ((1, "green"), (2, "blue")):
                grey = dataclasses.replace(pts, sigma_a=np.full(3, pts.sigma_a[ch]), sigma_s=np.full(3, pts.sigma_s[ch]))
                g_img = render(grey, a.spp, seed=2).astype(np.float64)[..., ch]
                bands = []
                for lo, hi in BANDS:
                    m = (elevation.reshape(rgb.shape[:2]) >= lo) & (elevation.reshape(rgb.shape[:2]) < hi)
                    pg, pr = g_img[m].mean(), rgb[..., ch][m].mean()
                    bands.append({"elevation_deg": [lo, hi], "pt_grey": round(pg, 7), "pt_rgb": round(pr, 7),
                                  "solve_over_grey": round(float(solved[m.ravel(), ch].mean() / pg), 3),
                                  "rgb_over_grey": round(float(pr / pg), 3)})
                row["channels"][name] = bands
            rows.append(row)
            print(json.dumps(row), flush=True)
    result = {"machine": machine_description(), "spp": a.spp, "photons": a.photons, "rows": rows}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "open_water_grey.json").write_text(json.dumps(result, indent=1) + "\n")
    head = "| water | depth m | channel | " + " | ".join(f"{lo:+g}..{hi:+g} deg" for lo, hi in BANDS) + " |"
    lines = [head, "|---|---|---|" + "---|" * len(BANDS)]
    for r in rows:
        for name, bands in r["channels"].items():
            cells = [f"{b['solve_over_grey']:.2f} / {b['rgb_over_grey']:.2f}" for b in bands]
            lines.append(f"| {r['water']} | {r['depth_m']:g} | {name} | " + " | ".join(cells) + " |")
    (a.out / "open_water_grey.md").write_text(
        f"Open water per channel ({a.spp} spp, {a.photons} photons, {result['machine']}): the path tracer with every "
        "channel given one channel's a and b (grey) as the reference; each cell is the solved column's band mean "
        "over it / the path tracer's RGB render's over it.\n\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
