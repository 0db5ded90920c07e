"""Fidelity against physics: seasynth's frames against a volumetric path tracer (Mitsuba 3) of the same scene.

A configuration is water x light: the water a Jerlov type or explicit `a=R,G,B/b=R,G,B/g=G`, the light `sun`
(sun and sky), `lamp` (two lamps on the vehicle, no sun or sky) or `sun+lamp`; `NAME=WATER:LIGHT[@DEPTH]` on the
command line. Each configuration's scene is the example's pinned frame with that water and light; it is exported
to the path tracer (meshes with their albedo, camera, sun/sky/lamps, a homogeneous medium with the water's a, b and
HG g under a flat surface) and rendered twice with different seeds: their mean is the reference and their PSNR to
each other the noise floor. Rows: every preset with every term, the paper's deferred model (in-air shading, its
three coefficients from the same water), and `default` with each term switched off.
"""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
import time
from pathlib import Path

import numpy as np

from seasynth.bench.accuracy import EXAMPLE, psnr_db, write_results
from seasynth.bench.fidelity_configs import (  # noqa: F401 (the configurations are the bench's public names)
    CONFIGS,
    DOF,
    LAMPS,
    LONG_VIEW,
    PRESET_NAMES,
    REFERENCES_PENDING,
    VIEWS,
    WORLD_CONFIGS,
)
from seasynth.bench.fidelity_scene import FRAME, SEED, paper_water, path_traced_scene
from seasynth.service.spec.dataset import DatasetSpec, apply_overrides, read_spec_file, spec_digest

# The table's frame size: the references at 320x240 are converged past every row's error, and seasynth's fixed
# cost per frame no longer dominates its time (at 160x120: bench/results/cpu/fidelity-resolution/160x120/).
WIDTH, HEIGHT = 320, 240
# Block PSNR: linear radiance averaged over BLOCK x BLOCK pixels, then 8-bit sRGB. A path-traced reference of
# multiply scattered lamp light converges slowly per pixel (its noise floor stays near 26 dB at 1.4e5 samples a pixel
# in turbid water), while its 8 x 8 block means are converged far beyond what is scored: the light model's error at
# the scale it works on (its terms are smooth in the image) is judged there.
BLOCK = 8


def config_options(text: str) -> tuple[str, frozenset[str]]:
    """'WATER:LIGHT[@DEPTH] [OPTION ...]' -> ('WATER:LIGHT[@DEPTH]', options): `textured` (the procedural textures
    on), `long` (a long view: a low camera pitch, the seabed out to where the water hides it, open water above),
    `port` (the camera behind a flat port: camera.port kind flat at its defaults),
    `particles` (marine snow at the water type's default density),
    `dof` (a thin lens, DOF: the path tracer's thinlens sensor, seasynth's depth of field)."""
    head, *options = text.split()
    unknown = sorted(set(options) - set(VIEWS))
    if unknown:
        raise SystemExit(f"configuration {text!r}: unknown option(s) {', '.join(unknown)}; known: {', '.join(VIEWS)}")
    return head, frozenset(options)


def parse_config(text: str) -> tuple[str, str, float]:
    """'WATER:LIGHT[@DEPTH] [OPTION ...]' -> (water, light, depth_m)."""
    water, _, rest = config_options(text)[0].partition(":")
    light, _, depth = rest.partition("@")
    if light not in ("sun", "lamp", "sun+lamp") or not water:
        raise SystemExit(f"configuration {text!r}: give WATER:LIGHT[@DEPTH], LIGHT one of sun, lamp, sun+lamp")
    return water, light, float(depth or 10.0)


def _water_overrides(water: str) -> dict:
    if "=" not in water:
        return {"water.jerlov": [water]}
    parts = dict(p.split("=", 1) for p in water.split("/"))
    out: dict = {"water.jerlov": []}
    for key, field in (("a", "water.absorption"), ("b", "water.scattering")):
        v = [float(x) for x in parts[key].split(",")]
        out[field] = {"min": v, "max": v}
    g = float(parts.get("g", 0.92))
    out["water.phase_g"] = [g, g]
    return out


def config_spec(text: str, size: tuple[int, int] = (WIDTH, HEIGHT)) -> DatasetSpec:
    """The configuration's spec; `size` (width, height) other than the table's for a look at how it scales."""
    water, light, depth = parse_config(text)
    options = config_options(text)[1]
    sun = "sun" in light
    overrides = {
        "seed": SEED, "frames": FRAME + 1, "camera.width": size[0], "camera.height": size[1],
        "water.model": "physical", "water.beta_jitter": [1.0, 1.0], "water.depth_m": [depth, depth],
        "lighting.sun_elevation_deg": [60.0, 60.0], "lighting.sun_azimuth_deg": [30.0, 30.0],
        "lighting.sun_intensity": [1.2, 1.2] if sun else [0.0, 0.0],
        "lighting.ambient": [0.25, 0.25] if sun else [0.0, 0.0],
        "lighting.lamps": LAMPS if "lamp" in light else [],
        # The tile alone in the near view: its references were rendered before the seabed reached the horizon
        # (terrain.far_field), which these frames do not see; the long view shows it.
        "terrain.far_field": "long" in options,
        # Vertex colours unless `textured`: the near view's first references were path traced before surfaces had
        # per-pixel textures (0.7.0).
        "materials.procedural": "textured" in options,
        **(LONG_VIEW if "long" in options else {}),
        **({"camera.port": {"kind": "flat"}} if "port" in options else {}),
        **({"water.particles.enabled": True} if "particles" in options else {}),
        **(DOF if "dof" in options else {}),
        **_water_overrides(water),
    }
    return DatasetSpec.model_validate(apply_overrides(read_spec_file(EXAMPLE), overrides))


def seasynth_rows(session, spec: DatasetSpec, repeats: int,
                  forward_scatter: bool = False) -> list[tuple[str, str, np.ndarray, float]]:
    """(preset, terms, linear float image, ms per frame) for each row of a configuration; forward_scatter: one more
    row, `default` with the forward-scatter blur (seasynth.worker.optics.forward_scatter; terms `+forward_scatter`)."""
    from seasynth.worker.frame.function import PRESETS
    from seasynth.worker.light.build import for_spec
    from seasynth.worker.optics import Optics
    from seasynth.worker.render import Passes

    scene = session.scene(spec, FRAME)
    view = session.view(spec, scene)
    items = Optics(spec, FRAME, scene, view, session.draw_items(scene)).shot.items  # with any particles
    light = scene.light
    variants = [(p, "full", light, None) for p in PRESET_NAMES]
    variants.append(("default", "paper", scene.lighting, paper_water(scene, view)))
    for term in ("sun_shadows", "sky", "scattering", "lamp_spread"):
        if getattr(light.terms, term):
            variants.append(("default", f"-{term}", dataclasses.replace(
                light, terms=dataclasses.replace(light.terms, **{term: False})), None))
    if light.terms.sun or light.terms.sky:  # the solved water column (water.solved_column) on, or off
        variants.append(("default", "-solved" if light.terms.solved else "+solved",
                         for_spec(light, not light.terms.solved), None))
    if light.terms.lamps:
        variants.append(("default", "-lamps", dataclasses.replace(
            light, terms=dataclasses.replace(light.terms, lamps=0)), None))
    if forward_scatter:
        variants.append(("default", "+forward_scatter", light, None))
    blurred = spec.model_copy(update={"water": spec.water.model_copy(update={"forward_scatter": True})})
    rows = []
    for preset, terms, lt, water in variants:
        # Every row through the spec's optical effects, as frames are made (a port's resampling, particles, ...).
        optics = Optics(blurred if terms == "+forward_scatter" else spec, FRAME, scene, view, items)
        needs = optics.shot.needs
        passes = Passes(clean="clean" in needs, ids="ids" in needs, range="range" in needs)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            image = optics.render(
                lambda v, drawn, lt=lt, water=water, preset=preset, passes=passes: session.renderer.render(
                    v, drawn, lt, water, PRESETS[preset], passes)).image
            times.append(time.perf_counter() - t0)
        rows.append((preset, terms, image, statistics.median(times) * 1e3))
    return rows


def mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))


def equal_error_spp(mse_seasynth: float, mse_halves: float, spp_half: int) -> float:
    """Samples per pixel at which a path-traced frame would score seasynth's error against the same reference.

    Path-tracing noise falls as 1/n: one sample's variance is s1 = spp_half * mse_halves / 2 (the halves differ by
    two halves' noise), the reference (their mean) holds s1 / (2 spp_half), and a frame of n samples scored against
    it has s1 / n + s1 / (2 spp_half). Where seasynth scores within the reference's own noise, n is at least the
    reference's 2 spp_half: that is returned (a lower bound). An extrapolation from the measured noise (finite
    variance assumed), not a render."""
    s1 = spp_half * mse_halves / 2.0
    rest = mse_seasynth - s1 / (2.0 * spp_half)
    return 2.0 * spp_half if rest <= s1 / (2.0 * spp_half) else s1 / rest


@dataclasses.dataclass(frozen=True)
class PathTracerCost:
    """A path-traced frame's seconds on this machine as a fixed part (loading the scene, tracing the integrator's
    kernel: paid once a frame) plus a part per sample per pixel."""

    fixed_s: float
    s_per_spp: float

    def seconds(self, spp: float) -> float:
        return self.fixed_s + self.s_per_spp * spp


def fit_cost(spp_low: int, s_low: float, spp_high: int, s_high: float) -> PathTracerCost:
    """The line through two timed renders (spp_high > spp_low), where both its parts are positive. Otherwise the
    longer render's own rate and no fixed part (a line through it, never above it): a longer render timed no slower,
    or one slower per sample than the shorter (large frames render in several calls of MAX_SAMPLES_PER_CALL)."""
    if spp_high <= spp_low:
        raise ValueError(f"fit_cost: spp_high ({spp_high}) must exceed spp_low ({spp_low})")
    per = (s_high - s_low) / (spp_high - spp_low)
    fixed = s_low - per * spp_low
    if per <= 0.0 or fixed < 0.0:
        return PathTracerCost(0.0, s_high / spp_high)
    return PathTracerCost(fixed, per)


def path_tracer_cost(pts, timing_spp: int) -> tuple[PathTracerCost, float]:
    """Times renders of `timing_spp` and 4x that (after a warm-up of `timing_spp`, which compiles the kernel) and
    fits PathTracerCost; returns it and the seconds of the `timing_spp` render. Scaling one short render's seconds
    by a sample count counts its fixed part once per `timing_spp` samples: 64 samples of clear-lamps took 2.3-2.5 s
    on a 2-core CPU, of which ~0.7 s fixed."""
    from seasynth.bench import pathtracer

    def timed(spp: int) -> float:
        t0 = time.perf_counter()
        pathtracer.render(pts, spp, seed=2)
        return time.perf_counter() - t0

    timed(timing_spp)
    low = timed(timing_spp)
    return fit_cost(timing_spp, low, 4 * timing_spp, timed(4 * timing_spp)), low


def block_means(image: np.ndarray, k: int = BLOCK) -> np.ndarray:
    """(h // k, w // k, 3): the means of k x k blocks of a linear image."""
    h, w = image.shape[0] // k * k, image.shape[1] // k * k
    return image[:h, :w].reshape(h // k, k, w // k, k, -1).mean(axis=(1, 3))


def reference_name(name: str, size: tuple[int, int]) -> str:
    """A configuration's scene and reference file stem: its name at the table's size, NAME-WxH at another."""
    return name if tuple(size) == (WIDTH, HEIGHT) else f"{name}-{size[0]}x{size[1]}"


def export_scenes(out: Path, *, configs: dict[str, str], platform: str,
                  size: tuple[int, int] = (WIDTH, HEIGHT)) -> list[Path]:
    """Writes each configuration's path-tracer scene to OUT/NAME.scene.npz (for `python -m seasynth.bench.reference`)."""
    from seasynth.bench.reference import SCENE_SUFFIX, save_scene
    from seasynth.worker.frame.function import RenderSession

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    with RenderSession(platform=platform) as session:
        for name, text in configs.items():
            paths.append(out / f"{reference_name(name, size)}{SCENE_SUFFIX}")
            save_scene(path_traced_scene(session, config_spec(text, size)), paths[-1])
    return paths


def stored_reference(references: Path | None, name: str, pts):
    """The stored reference of this configuration if one exists for exactly this scene, else None."""
    from seasynth.bench.reference import REF_SUFFIX, load_reference, same_scene, scene_digest

    path = references / f"{reference_name(name, (pts.width, pts.height))}{REF_SUFFIX}" if references else None
    if path is None or not path.exists():
        return None
    ref = load_reference(path)
    if not same_scene(ref, pts):
        raise SystemExit(f"{path}: rendered for another scene (sha256 {ref.scene_sha256[:12]}, this configuration's "
                         f"is {scene_digest(pts)[:12]}); re-export the scenes and render it again")
    return ref


def run(out: Path, *, configs: dict[str, str], spp: int, repeats: int, machine: str | None, platform: str,
        references: Path | None = None, timing_spp: int = 64, size: tuple[int, int] = (WIDTH, HEIGHT),
        forward_scatter: bool = False) -> dict:
    """Scores every configuration. Its reference is the stored one in `references` when there is one for this exact
    scene, else two renders of `spp` here. The path tracer's cost is always measured here (path_tracer_cost: a
    warm-up, then `timing_spp` and 4x `timing_spp` samples per pixel; a stored reference's own host and seconds are
    recorded beside them). forward_scatter: each configuration gets a `+forward_scatter` row (seasynth_rows)."""
    from seasynth.bench.reference import render_reference
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession
    from seasynth.worker.frame.srgb import encode_srgb8

    rows, pictures, sources = [], [], {}
    with RenderSession(platform=platform) as session:
        for name, text in configs.items():
            water, light, depth = parse_config(text)
            spec = config_spec(text, size)
            pts = path_traced_scene(session, spec)
            ref = stored_reference(references, name, pts) or render_reference(pts, spp, host="this machine")
            sources[name] = {"spp_per_half": ref.spp, "variant": ref.variant, "seconds": round(ref.seconds, 1),
                             "host": ref.host, "scene_sha256": ref.scene_sha256,
                             "lamp_housing_m": ref.lamp_housing_m}
            cost, pt_s = path_tracer_cost(pts, timing_spp)
            halves8 = [encode_srgb8(half) for half in ref.halves]
            floor, halves_mse = psnr_db(*halves8), mse(*halves8)
            floor_blocks = psnr_db(*(encode_srgb8(block_means(half)) for half in ref.halves))
            target = encode_srgb8(ref.mean)
            target_blocks = encode_srgb8(block_means(ref.mean))
            for preset, terms, linear, ms in seasynth_rows(session, spec, repeats, forward_scatter):
                image = encode_srgb8(linear)
                spp_eq = equal_error_spp(mse(image, target), halves_mse, ref.spp)
                diff = np.abs(image.astype(np.int64) - target.astype(np.int64))
                row = {"config": name, "water": water, "light": light, "depth_m": depth, "preset": preset,
                       "terms": terms, "psnr_db": round(psnr_db(image, target), 2), "mae": round(float(diff.mean()), 3),
                       "ms_per_frame": round(ms, 2), "path_tracer_s_per_frame": round(pt_s, 2),
                       "path_tracer_spp": timing_spp, "noise_floor_db": round(floor, 2),
                       "psnr_blocks_db": round(psnr_db(encode_srgb8(block_means(linear)), target_blocks), 2),
                       "path_tracer_fixed_s": round(cost.fixed_s, 3),
                       "path_tracer_ms_per_spp": round(cost.s_per_spp * 1e3, 3),
                       "path_tracer_equal_error_spp": round(spp_eq),
                       "path_tracer_equal_error_s": round(cost.seconds(spp_eq), 1),
                       "speedup_equal_error": round(cost.seconds(spp_eq) / (ms / 1e3)),
                       "noise_floor_blocks_db": round(floor_blocks, 2),
                       "spec_sha256": spec_digest(spec)}
                rows.append(row)
                print(json.dumps(row), flush=True)
                if preset == "default" and terms == "full":
                    pictures.append((name, target, image))
    result = {"machine": machine or machine_description(), "gl_renderer": session.renderer_name,
              "resolution": list(size), "path_tracer": "Mitsuba 3 volpath (max depth 64)",
              "timing": f"path tracer llvm_ad_rgb on this machine, {timing_spp} spp per frame",
              "timing_spp": timing_spp,
              "references": sources, "repeats": repeats, "configs": configs, "rows": rows}
    write_results(out, "fidelity", result, format_table(result), lambda path: picture(pictures, path))
    return result


def denoised_psnr_db(psnr_db: float, noise_floor_db: float) -> float:
    """The row's PSNR against a noiseless reference, estimated: the reference (the mean of two halves) carries a
    quarter of the halves' squared difference as noise of its own, uncorrelated with the row's error, so that much is
    taken off the row's squared error (+inf where nothing is left)."""
    mse = 10.0 ** (-psnr_db / 10.0) - 10.0 ** (-noise_floor_db / 10.0) / 4.0
    return round(-10.0 * math.log10(mse), 2) if mse > 0 else math.inf


def format_table(result: dict) -> str:
    keys = ("psnr_db", "psnr_denoised_db", "mae", "ms_per_frame", "path_tracer_s_per_frame", "noise_floor_db", "psnr_blocks_db",
            "noise_floor_blocks_db", "path_tracer_fixed_s", "path_tracer_ms_per_spp", "path_tracer_equal_error_s",
            "speedup_equal_error")
    lines = [
        f"# Fidelity against a path tracer ({result['resolution'][0]}x{result['resolution'][1]})",
        "",
        f"machine: {result['machine']}  ",
        f"GL renderer: {result['gl_renderer']}  ",
        f"path tracer: {result['path_tracer']}; {result['timing']}  ",
        "reference: the mean of two independent path-traced halves; noise floor: the halves' PSNR to each other "
        "(the mean's own error is about 6 dB below it); psnr_denoised_db: the PSNR against a noiseless reference, "
        "estimated by taking the reference's own noise (a quarter of the halves' squared difference) off the row's "
        "squared error (`denoised_psnr_db`)  ",
        f"ms_per_frame: median of {result['repeats']} renders; PSNR and MAE on 8-bit sRGB; psnr_blocks_db and "
        f"noise_floor_blocks_db: the same on {BLOCK}x{BLOCK} block means of linear radiance  ",
        "lamp housing: the radius of a water-free sphere round each lamp in the path tracer (bench/pathtracer.py "
        "`_lamp`), which bounds its fireflies; 0 where none  ",
        f"path_tracer_s_per_frame: one render of {result['timing_spp']} spp after a warm-up; "
        f"path_tracer_fixed_s and path_tracer_ms_per_spp: the line through renders of {result['timing_spp']} and "
        f"{4 * result['timing_spp']} spp (a frame's fixed cost, and its cost per sample per pixel)  ",
        "path_tracer_equal_error_s: the path tracer's seconds per frame on this machine at the samples per pixel "
        "where its error against the reference would equal the row's (extrapolated from the references' noise, "
        "`equal_error_spp`; at least the reference's own samples where the row is within the reference's noise): "
        "fixed_s + ms_per_spp x spp; speedup_equal_error: that over ms_per_frame",
        "",
        "| config | reference spp (x2) | variant | seconds | lamp housing m | host |",
        "|---|---|---|---|---|---|",
        *(f"| {n} | {r['spp_per_half']} | {r['variant']} | {r['seconds']} | {r.get('lamp_housing_m', 0.0)} | "
          f"{r['host']} |" for n, r in result["references"].items()),
        "",
        "| config | water | light | depth_m | preset | terms | " + " | ".join(keys) + " |",
        "|---|---|---|---|---|---|" + "---|" * len(keys),
    ]
    for r in result["rows"]:
        r = {**r, "psnr_denoised_db": denoised_psnr_db(r["psnr_db"], r["noise_floor_db"])}
        lines.append(f"| {r['config']} | {r['water']} | {r['light']} | {r['depth_m']} | {r['preset']} | {r['terms']} | "
                     + " | ".join(str(r[k]) for k in keys) + " |")
    return "\n".join(lines)


def picture(pictures, path: Path) -> None:
    """One row per configuration: path tracer | seasynth default | |error| x 4."""
    from PIL import Image, ImageDraw

    if not pictures:
        return
    h, w = pictures[0][1].shape[:2]
    sheet = Image.new("RGB", (3 * w, len(pictures) * (h + 12)), "white")
    draw = ImageDraw.Draw(sheet)
    for i, (name, ref, img) in enumerate(pictures):
        err = np.clip(np.abs(ref.astype(np.int64) - img.astype(np.int64)) * 4, 0, 255).astype(np.uint8)
        y = i * (h + 12)
        draw.text((2, y), f"{name}: path tracer | seasynth default | error x4", fill="black")
        for k, a in enumerate((ref, img, err)):
            sheet.paste(Image.fromarray(a), (k * w, y + 12))
    sheet.save(path)
