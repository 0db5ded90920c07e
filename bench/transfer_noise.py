"""The transfer test set's path-tracing noise: where it comes from and what exact shadow-ray transmittance buys.

For the first frame of each test group of a transfer recipe (rendered at a small size), two independent halves at
each samples-per-pixel count with Mitsuba's `volpath` ("tracked") and with pathtracer_integrator's exact shadow-ray
transmittance ("exact"): the halves' PSNR in 8-bit sRGB (the test set's noise_db), seconds, and whether the two
estimators' 8x8 block means agree within their noise; with --long-spp, noise_db of halves grown to many samples. Then, for the sunlit groups, noise_db with one light alone and without scattering, and how heavy the
tail of one pixel's samples is.

    python -m seasynth.bench.transfer_noise --out bench/results/cpu/transfer-noise [--width 96] [--spp 16,64,256]
    python -m seasynth.bench.transfer_noise --out ... --width 48 --long-spp 256,1024,4096,8192  (the long series)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

ESTIMATORS = {"tracked": False, "exact": True}
BLOCK = 8


def group_scenes(recipe_path: Path, width: int, height: int, groups: list[str] | None) -> list[tuple[str, object]]:
    """[(group name, PTScene of its frame 0 at width x height)] of the recipe's test groups (all, or those named)."""
    from seasynth.bench.fidelity_scene import exported_scene
    from seasynth.bench.transfer_recipe import held_out_specs, load_recipe
    from seasynth.bench.transfer_testset import held_out_scene
    from seasynth.worker.frame.function import RenderSession

    recipe = load_recipe(recipe_path).model_copy(update={"width": width, "height": height})
    out = []
    with RenderSession() as session:
        for group, spec in held_out_specs(recipe):
            if groups is None or group.name in groups:
                out.append((group.name, exported_scene(session, spec, held_out_scene(session, spec, 0))))
    return out


def noise_db(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) between two (h, w, 3) linear radiance images in 8-bit sRGB, as the test set records it."""
    from seasynth.bench.accuracy import psnr_db
    from seasynth.worker.frame.srgb import encode_srgb8

    return float(psnr_db(encode_srgb8(a.astype(np.float32)), encode_srgb8(b.astype(np.float32))))


def block_means(image: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """(h // block, w // block, 3) means of image (h, w, 3) over block x block tiles (a ragged edge dropped)."""
    h, w = (s // block * block for s in image.shape[:2])
    return image[:h, :w].reshape(h // block, block, w // block, block, 3).mean(axis=(1, 3))


def agreement(halves_a: list[np.ndarray], halves_b: list[np.ndarray]) -> dict:
    """How two estimators' images (each the mean of two halves) agree: per channel, the relative difference of the
    image means, and `z_rms`, the RMS of the block means' difference over the RMS its noise would give (from each
    estimator's halves: the mean of two halves has a quarter of their squared difference as its error): about 1
    when the expectations agree, larger when they differ."""
    ma, mb = (block_means((h[0] + h[1]) / 2) for h in (halves_a, halves_b))
    var = sum((block_means(h[0]) - block_means(h[1])) ** 2 / 4 for h in (halves_a, halves_b))
    mean_a, mean_b = ((h[0] + h[1]).mean(axis=(0, 1)) / 2 for h in (halves_a, halves_b))
    return {"mean_rel_diff": [round(float(x), 4) for x in (mean_b - mean_a) / np.maximum(mean_a, 1e-12)],
            "z_rms": [round(float(x), 3) for x in np.sqrt(((ma - mb) ** 2).mean(axis=(0, 1)) / var.mean(axis=(0, 1)))]}


def series(pt, spps: list[int], max_depth: int, housing: float, variant: str) -> dict:
    """Both estimators at each spp: noise_db, seconds; their agreement at the largest spp."""
    from seasynth.bench import pathtracer

    out: dict = {}
    last: dict = {}
    for name, exact in ESTIMATORS.items():
        rows = []
        for spp in spps:
            t0 = time.perf_counter()
            halves = pathtracer.render_seeds(pt, spp, (0, 1), max_depth=max_depth, variant=variant,
                                             lamp_housing_m=housing, exact_nee=exact)
            rows.append({"spp": spp, "noise_db": round(noise_db(*halves), 2),
                         "seconds": round(time.perf_counter() - t0, 2)})
            last[name] = halves
        out[name] = {"rows": rows}
    out["agreement"] = agreement(last["tracked"], last["exact"])
    return out


def convergence(pt, spps: list[int], max_depth: int, housing: float, variant: str) -> dict:
    """noise_db of each estimator's halves at each of the increasing spps, the halves grown by adding independent
    renders (seeds 2k, 2k + 1 for the k-th addition) to the previous ones."""
    from seasynth.bench import pathtracer

    out = {}
    for name, exact in ESTIMATORS.items():
        sums, done, rows = [0.0, 0.0], 0, []
        for k, spp in enumerate(spps):
            add = pathtracer.render_seeds(pt, spp - done, (2 * k, 2 * k + 1), max_depth=max_depth, variant=variant,
                                          lamp_housing_m=housing, exact_nee=exact)
            sums = [s + (spp - done) * a.astype(np.float64) for s, a in zip(sums, add)]
            done = spp
            rows.append({"spp": spp, "noise_db": round(noise_db(sums[0] / spp, sums[1] / spp), 2)})
        out[name] = rows
    return out


def parts(pt, spp: int, max_depth: int, housing: float, variant: str) -> dict:
    """noise_db at spp with the sun alone, the sky alone, the lamps alone and without scattering, each estimator."""
    from seasynth.bench import pathtracer

    z = np.zeros(3)
    cases = {"sun": {"sky_radiance_rgb": z, "lamps": ()}, "sky": {"sun_irradiance_rgb": z, "lamps": ()},
             "lamps": {"sun_irradiance_rgb": z, "sky_radiance_rgb": z}, "no-scattering": {"sigma_s": z}}
    out = {}
    for case, change in cases.items():
        if case == "lamps" and not pt.lamps:
            continue
        scene = dataclasses.replace(pt, **change)
        out[case] = {name: round(noise_db(*pathtracer.render_seeds(scene, spp, (0, 1), max_depth=max_depth,
                                                                    variant=variant, lamp_housing_m=housing,
                                                                    exact_nee=exact)), 2)
                     for name, exact in ESTIMATORS.items()}
    return out


def tail(pt, samples: int, max_depth: int, housing: float, variant: str) -> dict:
    """How heavy one pixel's sample distribution is (exact estimator, green): over all pixels, the share of each
    pixel's sum held by its top 1% of samples (median), and the fraction of samples above 10x and 100x the pixel's
    mean."""
    from seasynth.bench import pathtracer

    a = np.stack(pathtracer.render_seeds(pt, 1, tuple(range(samples)), max_depth=max_depth, variant=variant,
                                         lamp_housing_m=housing, exact_nee=True))[..., 1].astype(np.float64)
    mean = np.maximum(a.mean(axis=0), 1e-12)
    top = np.sort(a, axis=0)[::-1][: max(1, samples // 100)].sum(axis=0) / (mean * samples)
    x = a / mean
    return {"samples": samples, "top1pct_share_median": round(float(np.median(top)), 3),
            "above_10x_mean": round(float((x > 10).mean()), 4), "above_100x_mean": round(float((x > 100).mean()), 5)}


def machine() -> dict:
    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    return {"cpu": model, "nproc": os.cpu_count(), "platform": platform.platform()}


def table(result: dict) -> str:
    spps = result["spp"]
    lines = ["| group | estimator | " + " | ".join(f"{s} spp dB (s)" for s in spps) +
             " | blocks z_rms (R, G, B) | image mean diff (R, G, B) |",
             "|---|---|" + "---|" * (len(spps) + 2)]
    for g, r in result["groups"].items():
        for name in ESTIMATORS:
            cells = " | ".join(f"{x['noise_db']} ({x['seconds']})" for x in r[name]["rows"])
            agree = ("-", "-") if name == "tracked" else (r["agreement"]["z_rms"], r["agreement"]["mean_rel_diff"])
            lines.append(f"| {g} | {name} | {cells} | {agree[0]} | {agree[1]} |")
    lines += ["", f"noise_db at {result['parts_spp']} spp per half, one light alone or no scattering (tracked / exact):",
              "", "| group | sun | sky | lamps | no-scattering |", "|---|---|---|---|---|"]
    for g, p in result["parts"].items():
        lines.append(f"| {g} | " + " | ".join(f"{p[c]['tracked']} / {p[c]['exact']}" if c in p else "-"
                                               for c in ("sun", "sky", "lamps", "no-scattering")) + " |")
    lines += ["", "Tail of one pixel's samples (exact, green, 1 spp each):", ""]
    lines += [f"- {g}: {json.dumps(t)}" for g, t in result["tail"].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--recipe", type=Path, default=Path(__file__).parent / "recipes" / "transfer.json")
    p.add_argument("--width", type=int, default=96)
    p.add_argument("--spp", default="16,64,256")
    p.add_argument("--groups", default=None, help="comma-separated test groups (default: all)")
    p.add_argument("--parts-spp", type=int, default=64)
    p.add_argument("--tail-samples", type=int, default=256)
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--long-spp", default=None, help="only the long series: spp list, e.g. 1024,4096,8192")
    p.add_argument("--long-groups", default="clear-sun,ocean-sun")
    a = p.parse_args(argv)
    from seasynth.bench.transfer_recipe import load_recipe

    recipe = load_recipe(a.recipe)
    height = round(a.width * recipe.height / recipe.width)
    spps = [int(s) for s in a.spp.split(",")]
    depth, housing = recipe.test.max_depth, recipe.test.lamp_housing_m
    result: dict = {"machine": machine(), "recipe": a.recipe.name, "width": a.width, "height": height, "spp": spps,
                    "parts_spp": a.parts_spp, "groups": {}, "parts": {}, "tail": {}}
    a.out.mkdir(parents=True, exist_ok=True)
    if a.long_spp:
        long = {"machine": machine(), "width": a.width, "height": height, "groups": {}}
        for name, pt in group_scenes(a.recipe, a.width, height, a.long_groups.split(",")):
            long["groups"][name] = convergence(pt, [int(s) for s in a.long_spp.split(",")], depth, housing, a.variant)
            print(name, json.dumps(long["groups"][name]), flush=True)
            (a.out / "transfer-noise-long.json").write_text(json.dumps(long, indent=1) + "\n")
        return
    for name, pt in group_scenes(a.recipe, a.width, height, a.groups.split(",") if a.groups else None):
        result["groups"][name] = series(pt, spps, depth, housing, a.variant)
        if np.any(pt.sun_irradiance_rgb > 0):
            result["parts"][name] = parts(pt, a.parts_spp, depth, housing, a.variant)
            result["tail"][name] = tail(pt, a.tail_samples, depth, housing, a.variant)
        print(name, json.dumps(result["groups"][name]), flush=True)
        (a.out / "transfer-noise.json").write_text(json.dumps(result, indent=1) + "\n")
    (a.out / "transfer-noise.md").write_text(f"# Transfer test set noise ({a.width}x{height}, {a.variant}; "
                                             f"{result['machine']['cpu']}, {result['machine']['nproc']} cores)\n\n"
                                             + table(result))


if __name__ == "__main__":
    main()
