"""Water calibration accuracy: seasynth's own clean frames and range, hazed with known water (Jerlov types and
off-family waters made from them, noise on and off), estimated back by seasynth.service.calibration.estimate with range (the default,
with its Jerlov prior, and the free fit) and without range; error per coefficient and channel.

The haze is applied here in float64 per pixel (seasynth.worker.frame.formation.haze) to the frame's clean image, camera noise
(Gaussian, linear, seeded) is added, and the result is encoded to 8-bit sRGB once: the estimator sees what a photo
of that water would hold, and the truth is exact.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from seasynth.bench.calibration_floor import apparent_attenuation, floor_summary, format_floor
from seasynth.service.spec.dataset import DatasetSpec, apply_overrides, read_spec_file, spec_digest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
WIDTH, HEIGHT = 160, 120
FRAMES = 3
CHANNELS = ("R", "G", "B")
# Scenes: overrides on the example spec. seabed-forward: a camera 1-2 m above an 80 m seabed looking forward (range
# about 1.5-40 m, open water above the horizon). urchins: the example's own cameras (range about 0.6-9 m).
SCENES: dict[str, dict] = {
    "seabed-forward": {
        "terrain.size_m": 80.0,
        "terrain.cells": 128,
        "workspaces.camera": {"min": [-1.0, -2.0, 1.0], "max": [1.0, -1.8, 2.0]},
        "workspaces.look_at": {"min": [-2.0, 6.0, 0.0], "max": [2.0, 12.0, 0.5]},
    },
    "urchins": {},
}
# The table's clean frames are lit as the paper's model lights them (in air: J does not change with range), the
# estimator's own assumption. Under the physical model (--light physical; its table apart) J falls with depth as the
# sun's light does.
LIGHTS = ("paper", "physical")  # the clean frames' light model (water.model); the table's is the first
WATERS = ("I", "II", "3C", "5C", "9C")
OFF_FAMILY = "~"  # "3C~": 3C's beta_D with each channel scaled by 1 +- U(0.15, 0.25) (seeded per type): no Jerlov type
OFF_FAMILY_SPREAD = (0.15, 0.25)
OFF_RATIO_SPREAD = (0.1, 0.2)  # "3C~" also: beta_B / beta_D = 0.9 (1 +- U(0.1, 0.2)) per channel, seeded
PRIORS = (None, "none")  # with-range estimates: the default (the Jerlov prior) and the free fit (prior "none")
BACKSCATTER_RATIO = 0.9  # beta_B = 0.9 beta_D, the middle of the spec's default backscatter_ratio
NOISE = (0.0, 0.01)  # Gaussian sigma, linear light
BOOTSTRAP = 16
TARGET_B_INF_ABS = 0.02
TARGET_BETA_REL = 0.10


def scene_spec(name: str, width: int, height: int, light: str = LIGHTS[0]) -> DatasetSpec:
    base = read_spec_file(EXAMPLE)
    # terrain.far_field off: the scenes' open water above the horizon is what identifies B_inf (as designed, before
    # the seabed reached the horizon in 0.6.0); vertex colours, as the scenes were before textures (0.7.0)
    overrides = {"frames": FRAMES, "camera.width": width, "camera.height": height, "quality": "fast",
                 "outputs.clean": True, "outputs.range": True, "water.model": light, "terrain.far_field": False,
                 "materials.procedural": False,
                 **SCENES[name]}
    return DatasetSpec.model_validate(apply_overrides(base, overrides))


def clean_and_range(session, spec: DatasetSpec, index: int) -> tuple[np.ndarray, np.ndarray]:
    """The frame's clean image J: (h, w, 3) float64 linear, and range: (h, w) float64 metres, +inf open water."""
    from seasynth.worker.frame.function import PRESETS, scene_light
    from seasynth.worker.render import Passes

    scene = session.scene(spec, index)
    view = session.view(spec, scene)
    items = session.draw_items(scene)
    r = session.renderer.render(view, items, scene_light(scene), scene.water, PRESETS[spec.quality],
                                Passes(clean=True, range=True))
    return r.clean.astype(np.float64), r.range_m.astype(np.float64)


def water_beta(water: str) -> np.ndarray:
    """beta_D (3,) 1/m of a bench water: a Jerlov type's, or for "<type>~" that type's with each channel scaled by
    1 + s U(0.15, 0.25), s = +-1, from a generator seeded by the type (the same on every run)."""
    from seasynth.service.water import JERLOV_TYPES, jerlov_beta

    base = water.removesuffix(OFF_FAMILY)
    bd = jerlov_beta(base)
    if water.endswith(OFF_FAMILY):
        rng = np.random.default_rng(np.random.SeedSequence([JERLOV_TYPES.index(base), 0x0FF]))
        bd = bd * (1 + rng.choice([-1.0, 1.0], 3) * rng.uniform(*OFF_FAMILY_SPREAD, 3))
    return bd


def water_backscatter_ratio(water: str) -> np.ndarray:
    """beta_B / beta_D (3,) of a bench water: BACKSCATTER_RATIO in every channel, or for "<type>~" BACKSCATTER_RATIO
    times 1 + s_c U(0.1, 0.2) per channel, signs s_c = +-1 with both signs present, seeded by the type (a stream
    apart from water_beta's): a ratio that differs by channel (by 20-40% between some two), which the default
    estimator's prior (one ratio for all channels) does not hold."""
    from seasynth.service.water import JERLOV_TYPES

    ratio = np.full(3, BACKSCATTER_RATIO)
    if water.endswith(OFF_FAMILY):
        base = water.removesuffix(OFF_FAMILY)
        rng = np.random.default_rng(np.random.SeedSequence([JERLOV_TYPES.index(base), 0xB5]))
        signs = rng.permutation([1.0, -1.0, rng.choice([-1.0, 1.0])])
        ratio = ratio * (1 + signs * rng.uniform(*OFF_RATIO_SPREAD, 3))
    return ratio


def hazed_photo(J: np.ndarray, range_m: np.ndarray, water: str, sigma: float, seed: int) -> tuple[np.ndarray, dict]:
    """8-bit sRGB photo (h, w, 3) uint8 of J through bench water `water` (see water_beta), with Gaussian noise sigma
    (linear), and the truth {beta_D, beta_B, B_inf: (3,) lists}."""
    from seasynth.service.water import jerlov_veiling_light
    from seasynth.worker.frame.formation import haze
    from seasynth.worker.frame.srgb import encode_srgb8

    bd = water_beta(water)
    truth = {"beta_D": bd, "beta_B": water_backscatter_ratio(water) * bd,
             "B_inf": jerlov_veiling_light(water.removesuffix(OFF_FAMILY))}
    image = haze(J, range_m, truth["beta_D"], truth["beta_B"], truth["B_inf"], np.float64)
    if sigma > 0:
        image = image + np.random.default_rng(seed).normal(0.0, sigma, image.shape)
    return encode_srgb8(image), {k: v.tolist() for k, v in truth.items()}


def noise_seed(scene: str, index: int, water: str) -> int:
    """The noise generator's seed of one photo: from its scene, frame and water, whichever others are run."""
    from seasynth.service.water import JERLOV_TYPES

    off = 500 if water.endswith(OFF_FAMILY) else 0
    return 100_000 * list(SCENES).index(scene) + 1000 * index + off + JERLOV_TYPES.index(water.removesuffix(OFF_FAMILY))


def errors(estimate, truth: dict) -> dict:
    """Per channel: relative error of beta_D, beta_B (None where not identified), absolute error of B_inf, and
    relative error of the beta_B ratios to green (None where not identified)."""
    def rel(got, want):
        return [None if g is None else abs(g - w) / w for g, w in zip(got, want)]

    ratio_true = [b / truth["beta_B"][1] for b in truth["beta_B"]]
    return {
        "beta_D_rel": rel(estimate.beta_D.value, truth["beta_D"]),
        "beta_B_rel": rel(estimate.beta_B.value, truth["beta_B"]),
        "B_inf_abs": [None if g is None else abs(g - w) for g, w in zip(estimate.B_inf.value, truth["B_inf"])],
        "beta_B_ratio_rel": [None if c == 1 else e
                             for c, e in enumerate(rel(estimate.beta_B_ratio.value, ratio_true))],
    }


def summarise(rows: list[dict], with_range: bool, noise: float | None, scene: str | None = None,
              water: str | None = None, *, prior: str | None = None, off_family: bool = False) -> dict:
    """Median and p90 of each error per channel over the rows (noise, scene, water None: all of the family), and
    the share identified. prior: the estimator's prior (with range); off_family: the "<type>~" waters, else the
    Jerlov ones."""
    mine = [r for r in rows if r["with_range"] == with_range and (noise is None or r["noise"] == noise)
            and (scene is None or r["scene"] == scene) and (water is None or r["water"] == water)
            and r.get("prior") == prior and r["water"].endswith(OFF_FAMILY) == off_family]
    out = {"scene": scene, "water": water, "with_range": with_range, "noise": noise, "prior": prior,
           "off_family": off_family, "estimates": len(mine)}
    for key in ("beta_D_rel", "beta_B_rel", "B_inf_abs", "beta_B_ratio_rel"):
        per = {}
        for c, name in enumerate(CHANNELS):
            vals = [r["errors"][key][c] for r in mine if r["errors"][key][c] is not None]
            per[name] = {"identified": f"{len(vals)}/{len(mine)}",
                         "median": round(float(np.median(vals)), 4) if vals else None,
                         "p90": round(float(np.percentile(vals, 90)), 4) if vals else None}
        out[key] = per
    return out


def run(out: Path | None, *, scenes=None, waters=None, frames: int = FRAMES, width: int = WIDTH,
        height: int = HEIGHT, machine: str | None = None, platform: str = "egl", light: str = LIGHTS[0]) -> dict:
    import time

    from seasynth.bench.throughput import machine_description
    from seasynth.service.calibration.estimate import estimate_water
    from seasynth.worker.frame.function import RenderSession

    scenes, waters = scenes or list(SCENES), waters or list(WATERS)
    photos = [*waters, *(w + OFF_FAMILY for w in waters)]
    if light not in LIGHTS:
        raise SystemExit(f"unknown light {light!r}; known: {', '.join(LIGHTS)}")
    for name in scenes:
        if name not in SCENES:
            raise SystemExit(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    rows, seconds, clean_frames = [], {None: [], "none": [], "no_range": []}, []
    with RenderSession(platform=platform) as session:
        renderer = session.renderer_name
        for scene in scenes:
            spec = scene_spec(scene, width, height, light)
            for index in range(frames):
                J, range_m = clean_and_range(session, spec, index)
                finite = range_m[np.isfinite(range_m)]
                clean_frames.append({"scene": scene, "frame": index,
                                     "range_m": [round(float(finite.min()), 3), round(float(finite.max()), 3)],
                                     "apparent_beta": apparent_attenuation(J, range_m).round(5).tolist()})
                for water in photos:
                    for sigma in NOISE:
                        photo, truth = hazed_photo(J, range_m, water, sigma, seed=noise_seed(scene, index, water))
                        for with_range, prior in ((True, None), (True, "none"), (False, None)):
                            t = time.perf_counter()
                            est = estimate_water(photo, range_m if with_range else None, seed=index,
                                                 bootstrap=BOOTSTRAP, prior=prior)
                            seconds[prior if with_range else "no_range"].append(time.perf_counter() - t)
                            row = {"scene": scene, "frame": index, "water": water, "noise": sigma,
                                   "with_range": with_range, "prior": prior, "truth": truth,
                                   "estimate": est.as_dict(), "errors": errors(est, truth)}
                            rows.append(row)
                print(json.dumps({"scene": scene, "frame": index, "estimates": len(rows)}), flush=True)
    summary = [summarise(rows, wr, n) for wr in (True, False) for n in (None, *NOISE)]
    summary += [summarise(rows, wr, None, sc) for sc in scenes for wr in (True, False)]
    summary += [summarise(rows, True, None, water=w) for w in waters]
    for prior in PRIORS:
        for off in (False, True):
            if prior is None and not off:
                continue  # the rows above
            summary += [summarise(rows, True, n, prior=prior, off_family=off) for n in (None, *NOISE)]
            summary += [summarise(rows, True, None, water=w + (OFF_FAMILY if off else ""), prior=prior,
                                  off_family=off) for w in waters]
    result = {
        "machine": machine or machine_description(), "gl_renderer": renderer, "resolution": [width, height],
        "frames_per_scene": frames, "waters": waters, "backscatter_ratio": BACKSCATTER_RATIO, "noise": list(NOISE),
        "off_family_beta_D": {w + OFF_FAMILY: water_beta(w + OFF_FAMILY).round(4).tolist() for w in waters},
        "off_family_backscatter_ratio": {w + OFF_FAMILY: water_backscatter_ratio(w + OFF_FAMILY).round(4).tolist()
                                         for w in waters},
        "bootstrap": BOOTSTRAP, "clean_light": light,
        "scene_spec_sha256": {s: spec_digest(scene_spec(s, width, height, light)) for s in scenes},
        "seconds_per_estimate": {{None: "with_range", "none": "with_range_free_fit", "no_range": "without_range"}[k]:
                                 round(float(np.median(v)), 3) for k, v in seconds.items() if v},
        "targets": {"B_inf_abs_median": TARGET_B_INF_ABS, "beta_rel_median": TARGET_BETA_REL},
        "summary": summary, "clean_frames": clean_frames,
        "floor_beta_D": {w: water_beta(w).round(4).tolist() for w in photos},
        "floor": floor_summary(clean_frames, {w: water_beta(w).tolist() for w in photos}),
        "rows": rows,
    }
    result["targets_met"] = targets_met(result)
    result["targets_met_other"] = {f"{'free fit (prior none)' if p else 'default'}, "
                                   f"{'off-family' if o else 'Jerlov'} waters":
                                   targets_met(result, prior=p, off_family=o)
                                   for p in PRIORS for o in (False, True) if p or o}
    table = format_table(result)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "calibration.json").write_text(json.dumps(result, indent=1) + "\n")
        (out / "calibration.md").write_text(table + "\n")
    print(table)
    return result


def targets_met(result: dict, prior: str | None = None, off_family: bool = False) -> dict:
    """With range, over all rows (default: the default estimator on the Jerlov waters): each channel's median B_inf
    error <= 0.02 and median beta_D and beta_B relative error <= 10% (over the identified estimates)."""
    s = next(x for x in result["summary"]
             if x["with_range"] and x["noise"] is None and x["scene"] is None and x["water"] is None
             and x.get("prior") == prior and x.get("off_family", False) == off_family)
    met = {}
    for c in CHANNELS:
        b = s["B_inf_abs"][c]["median"]
        met[f"B_inf {c}"] = b is not None and b <= TARGET_B_INF_ABS
        for key in ("beta_D_rel", "beta_B_rel"):
            m = s[key][c]["median"]
            met[f"{key.split('_rel')[0]} {c}"] = m is not None and m <= TARGET_BETA_REL
    return met


def _cell(d: dict) -> str:
    if d["median"] is None:
        return f"- ({d['identified']})"
    return f"{d['median']:.3g} / {d['p90']:.3g} ({d['identified']})"


def format_table(result: dict) -> str:
    light = result.get("clean_light", LIGHTS[0])
    lines = [
        f"# Water calibration accuracy ({result['resolution'][0]}x{result['resolution'][1]})",
        "",
        f"machine: {result['machine']}  ",
        f"GL renderer: {result['gl_renderer']}  ",
        f"clean frames lit by the {light} model"
        + (" (in air: J does not change with range)" if light == "paper" else
           " (J falls with depth as the sun's light does, which the estimator's prior excludes)") + "  ",
        f"frames: {result['frames_per_scene']} per scene ({', '.join(result['scene_spec_sha256'])}); waters: Jerlov "
        f"{', '.join(result['waters'])} (beta_B = {result['backscatter_ratio']} beta_D) and off-family waters (type~: "
        "each channel's beta_D scaled by 1 +- 15-25%, seeded: "
        + ", ".join(f"{k} {v}" for k, v in result["off_family_beta_D"].items())
        + f"; and beta_B / beta_D = {result['backscatter_ratio']} (1 +- 10-20%), differing by channel: "
        + ", ".join(f"{k} {v}" for k, v in result["off_family_backscatter_ratio"].items())
        + "), B_inf the type's default; "
        f"noise sigma (linear): {', '.join(str(n) for n in result['noise'])}  ",
        f"seconds per estimate (median, {result['bootstrap']} bootstrap resamples): "
        + ", ".join(f"{k} {v}" for k, v in result["seconds_per_estimate"].items()),
        "",
        "Each cell: median / p90 of the error over the estimates that identified it (identified / estimates). "
        "beta: relative error; B_inf: absolute error, linear; ratio: relative error of beta_B_c / beta_B_G. "
        "range: yes (the default estimator, with its Jerlov prior), yes, free (prior none: each channel fitted "
        "freely), no; water: all (the Jerlov waters), all~ (the off-family waters) or one water.",
        "",
        "| scene | water | range | noise | quantity | R | G | B |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in result["summary"]:
        noise = "all" if s["noise"] is None else str(s["noise"])
        scene = s["scene"] or "all"
        water = s["water"] or ("all~" if s.get("off_family") else "all")
        how = ("yes, free" if s.get("prior") == "none" else "yes") if s["with_range"] else "no"
        keys = ("beta_D_rel", "beta_B_rel", "B_inf_abs") if s["with_range"] else ("B_inf_abs", "beta_B_ratio_rel")
        for key in keys:
            name = {"beta_D_rel": "beta_D", "beta_B_rel": "beta_B", "B_inf_abs": "B_inf",
                    "beta_B_ratio_rel": "beta_B ratio"}[key]
            lines.append(f"| {scene} | {water} | {how} | {noise} | {name} | "
                         + " | ".join(_cell(s[key][c]) for c in CHANNELS) + " |")
    met = result["targets_met"]
    lines += ["", "Targets with range (all rows, median): B_inf within 0.02, beta within 10% per channel: "
              + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in met.items())]
    for label, other in result.get("targets_met_other", {}).items():
        lines += ["", f"The same targets, {label}: "
                  + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in other.items())]
    lines += format_floor(result)
    return "\n".join(lines)
