"""Open water of the renderer's model against the path tracer's stored band means (bench/results/cpu/open-water/
open_water.json, written by bench/open_water.py): the float64 twin of the resolve shader (`worker.light.volume`)
with and without the solved water column (`worker.light.solved`), on the same 8 x 48 views, waters and depths.

    python -m seasynth.bench.open_water_model [--reference FILE] [--out DIR] [--waters I,II,...]

Pixels are averaged over 3 x 3 positions each (the path tracer's box filter). Writes DIR/open_water_model.json, .md:
the model's mean radiance over the path tracer's per elevation band (green, blue) for each model, and the seconds
the solved columns took (once per process; every depth of a water reads the same columns).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from seasynth.bench.open_water_column import REFERENCE, table, views

MODELS = ("K", "solved")  # today's view-ray scattering (K on both legs), the solved column's


def radiance(light, cam_depth: float, dirs: np.ndarray) -> np.ndarray:
    """(n, 3) pixel means of the twin's open water along world directions (n, 9, 3)."""
    from seasynth.worker.light.volume import volume

    flat = dirs.reshape(-1, 3)
    out = volume(np.zeros((len(flat), 3)), np.full(len(flat), np.inf), flat, flat, cam_depth, light)
    return out.reshape(dirs.shape[0], dirs.shape[1], 3).mean(axis=1)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--reference", type=Path, default=REFERENCE)
    p.add_argument("--out", type=Path, default=Path("bench/results/cpu/open-water-model"))
    p.add_argument("--waters", default="I,II,III,1C,3C,5C,7C,9C")
    a = p.parse_args(argv)
    from seasynth.bench.open_water import BANDS
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession
    from seasynth.worker.light.solved import with_column

    ref = json.loads(a.reference.read_text())
    rows, solve_s = [], []
    with RenderSession() as session:
        for r in (r for r in ref["rows"] if r["water"] in a.waters.split(",")):
            light, cam_depth, dirs, elevation = views(session, r["water"], r["depth_m"])
            row = {"water": r["water"], "depth_m": r["depth_m"]}
            for model in MODELS:
                lt = with_column(light, model == "solved")
                t0 = time.perf_counter()
                image = radiance(lt, cam_depth, dirs)
                if model == "solved":
                    solve_s.append(time.perf_counter() - t0)
                ratios = []
                for (lo, hi), band in zip(BANDS, r["bands"]):
                    m = (elevation >= lo) & (elevation < hi)
                    pt = np.asarray(band["path_tracer"], dtype=np.float64)
                    q = image[m].mean(axis=0)
                    ratios.append(np.where(pt > 1e-6, q / np.maximum(pt, 1e-12), np.nan).round(3).tolist())
                row[model] = ratios
                logs = np.abs(np.log(np.asarray(ratios, dtype=np.float64)[:, 1:]))
                row[f"{model}_log_error"] = round(float(np.nanmean(logs)), 3) if np.isfinite(logs).any() else None
            rows.append(row)
            print(json.dumps(row), flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    result = {"machine": machine_description(), "reference": str(a.reference), "reference_spp": ref["spp"],
              "seconds_first_frame_of_a_water": [round(s, 2) for s in solve_s], "rows": rows}
    (a.out / "open_water_model.json").write_text(json.dumps(result, indent=1) + "\n")
    (a.out / "open_water_model.md").write_text(report(result))
    print(report(result))


def report(result: dict) -> str:
    """The markdown of a result (open_water_model.json's content)."""
    both = [r for r in result["rows"] if all(r[f"{m}_log_error"] is not None for m in MODELS)]
    err = {m: np.mean([r[f"{m}_log_error"] for r in both]) for m in MODELS}
    s = result["seconds_first_frame_of_a_water"]
    return (f"Open water of the renderer's float64 twin against the path tracer's band means of "
            f"`{result['reference']}` ({result['reference_spp']} spp), {result['machine']}: the model's mean radiance "
            "over the path tracer's per elevation band, green and blue (nan: the path tracer's stored mean is below "
            "1e-6). Mean |log ratio| over the bands, green and blue, of every water and depth with a defined ratio: "
            + ", ".join(f"{m} {err[m]:.3f}" for m in MODELS)
            + f". The solved model's twin took {min(s):.2f}-{max(s):.2f} s per water and depth, solves included "
            "(the columns are kept per process: a water's later depths and frames reuse them).\n\n"
            "Today's model (K on the view leg, the downwelling light scattered as a beam):\n\n"
            + table(result["rows"], "K") + "\n\nThe solved column (single scattering through c, J_ms / (c - K_J w_z)):"
            "\n\n" + table(result["rows"], "solved") + "\n")


if __name__ == "__main__":
    main()
