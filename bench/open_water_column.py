"""Open water from the water column's solved light field (`worker.light.column`) against the path tracer's stored
band means (bench/results/cpu/open-water/open_water.json, written by bench/open_water.py): the same 8 x 48 views,
waters and depths, the solve's mean radiance per elevation band over the path tracer's, green and blue.

    python -m seasynth.bench.open_water_column [--photons N] [--reference FILE] [--out DIR] [--waters I,II,...]

Each water is solved once per channel down to past the deepest camera (every depth reads the same column), twice:
with the path tracer's cap on scatterings (its max_depth of 64 path vertices: at most 63 scatterings), which is the
like-for-like comparison, and without, which shows what the cap takes from the path tracer in deep turbid water.
Pixels are averaged over 3 x 3 positions each (the path tracer's box filter). Writes DIR/open_water_column.json, .md.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

PT_MAX_SCATTERINGS = 63  # bench/pathtracer.py renders with max_depth 64
REFERENCE = Path("bench/results/cpu/open-water/open_water.json")


def views(session, water: str, depth_m: float):
    """(light, camera depth m, (n, 9, 3) world directions of 3 x 3 positions in each pixel, (n,) centre elevations)."""
    from seasynth.bench.fidelity import FRAME
    from seasynth.bench.open_water import HEIGHT, WIDTH, open_water_spec
    from seasynth.worker.light.volume import camera_depth

    spec = open_water_spec(water, depth_m)
    scene = session.scene(spec, FRAME)
    K = session.view(spec, scene).K
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    off = np.array([-1.0, 0.0, 1.0]) / 3.0
    du, dv = (x.ravel() for x in np.meshgrid(off, off))
    pix = np.stack([u.ravel()[:, None] + du, v.ravel()[:, None] + dv, np.ones((u.size, 9))], axis=-1)
    d = pix @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    dirs = d @ scene.world_from_cam[:3, :3].T
    centre = dirs[:, 4]
    return scene.light, camera_depth(scene.light, scene.world_from_cam), dirs, np.degrees(np.arcsin(centre[:, 2]))


def solve_water(light, deepest_m: float, photons: int, max_order: int | None, seed: int) -> list:
    """The three channels' columns of one water (sun and sky as the path tracer gets them), each down to 8 / K (at
    most 400 m) past the deepest camera, and the seconds each took."""
    from seasynth.worker.light.column import solve
    from seasynth.worker.light.sky import window_radiance

    m = light.medium
    sky = window_radiance(light.sky_irradiance)
    rng = np.random.default_rng(seed)
    out = []
    for ch in range(3):
        t0 = time.perf_counter()
        col = solve(float(m.a[ch]), float(m.b[ch]), float(m.g), float(light.sun_dir_world[2]),
                    math.pi * float(light.sun_irradiance[ch]), float(sky[ch]),
                    deepest_m + min(8.0 / float(m.k[ch]), 400.0), rng, photons, max_order=max_order)
        out.append((col, time.perf_counter() - t0))
    return out


def radiance(cols: list, light, cam_depth: float, dirs: np.ndarray) -> np.ndarray:
    """(n, 3) pixel means of path radiance plus the window's unscattered sky."""
    from seasynth.worker.light.column import path_radiance, to_sun_frame, window_radiance

    v = to_sun_frame(dirs.reshape(-1, 3), light.sun_dir_world)
    per = [path_radiance(col, v, cam_depth) + window_radiance(col, v, cam_depth) for col, _ in cols]
    return np.stack(per, axis=-1).reshape(dirs.shape[0], dirs.shape[1], 3).mean(axis=1)


def table(rows: list[dict], key: str) -> str:
    from seasynth.bench.open_water import BANDS

    head = ("| water | depth m | " + " | ".join(f"{lo:+g}..{hi:+g} deg (G, B)" for lo, hi in BANDS)
            + " |\n|---|---|" + "---|" * len(BANDS))
    lines = [head]
    for r in rows:
        cells = [", ".join(f"{v:.2f}" if not v >= 100 else ">100" for v in x[1:]) for x in r[key]]
        lines.append(f"| {r['water']} | {r['depth_m']:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--photons", type=int, default=80000)
    p.add_argument("--reference", type=Path, default=REFERENCE)
    p.add_argument("--out", type=Path, default=Path("bench/results/cpu/open-water-column"))
    p.add_argument("--waters", default="I,II,III,1C,3C,5C,7C,9C")
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args(argv)
    from seasynth.bench.open_water import BANDS
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession

    ref = json.loads(a.reference.read_text())
    waters = a.waters.split(",")
    rows, seconds = [], []
    with RenderSession() as session:
        for water in waters:
            pts = [r for r in ref["rows"] if r["water"] == water]
            if not pts:
                continue
            light = views(session, water, pts[0]["depth_m"])[0]
            deepest = max(views(session, water, r["depth_m"])[1] for r in pts)
            capped = solve_water(light, deepest, a.photons, PT_MAX_SCATTERINGS, a.seed)
            free = solve_water(light, deepest, a.photons, None, a.seed + 1)
            seconds += [s for _, s in capped + free]
            for r in pts:
                light, cam_depth, dirs, elevation = views(session, water, r["depth_m"])
                lc, lf = radiance(capped, light, cam_depth, dirs), radiance(free, light, cam_depth, dirs)
                row = {"water": water, "depth_m": r["depth_m"], "solve_capped": [], "ratio": [], "uncapped_over_capped": []}
                for (lo, hi), band in zip(BANDS, r["bands"]):
                    m = (elevation >= lo) & (elevation < hi)
                    pt = np.asarray(band["path_tracer"], dtype=np.float64)
                    qc, qf = lc[m].mean(axis=0), lf[m].mean(axis=0)
                    row["solve_capped"].append(qc.round(6).tolist())
                    row["ratio"].append(np.where(pt > 1e-6, qc / np.maximum(pt, 1e-12), np.nan).round(3).tolist())
                    row["uncapped_over_capped"].append((qf / np.maximum(qc, 1e-300)).round(3).tolist())
                rows.append(row)
                print(json.dumps({"water": water, "depth_m": r["depth_m"], "ratio": row["ratio"]}), flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    result = {"machine": machine_description(), "photons": a.photons, "seed": a.seed, "reference": str(a.reference),
              "reference_spp": ref["spp"], "seconds_per_channel_solve": {
                  "median": round(float(np.median(seconds)), 2), "max": round(float(np.max(seconds)), 2)}, "rows": rows}
    (a.out / "open_water_column.json").write_text(json.dumps(result, indent=1) + "\n")
    (a.out / "open_water_column.md").write_text(report(result))
    print(report(result))


def report(result: dict) -> str:
    """The markdown of a result (open_water_column.json's content)."""
    t = result["seconds_per_channel_solve"]
    return (f"Open water from the solved water column (`worker/light/column.py`, {result['photons']} photons per "
            f"channel, {result['machine']}; one channel's solve, down to 8 / K past the deepest camera, took {t['median']}"
            f" s median, {t['max']} s at most, the machine shared with other work) against the path tracer's band "
            f"means of `{result['reference']}` ({result['reference_spp']} spp).\n\nThe solve's mean radiance over the "
            "path tracer's per elevation band, green and blue, the solve capped at the path tracer's 63 scatterings "
            "(nan: the path tracer's stored mean is below 1e-6; its means are stored to 6 decimals, so means below "
            "~1e-4, at 25 m in turbid water, carry rounding as well as its noise):\n\n"
            + table(result["rows"], "ratio") + "\n\nWhat the cap takes: the uncapped solve over the capped one (1 "
            "where no light scattered more than 63 times reaches the camera; two independent solves, so a few % is "
            "the photons' noise):\n\n" + table(result["rows"], "uncapped_over_capped") + "\n")


if __name__ == "__main__":
    main()
