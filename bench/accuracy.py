"""Accuracy against time: each quality preset against a 16-sample float64 reference, on pinned hard scenes.

Reference: the same scene at 4x4 samples per pixel (a regular grid), range per sample, the water applied per sample
in float64, averaged in linear light and encoded to 8-bit sRGB once. Reference labels come from the majority id of
each pixel's 16 samples (see majority_ids and errors for exactly what the label columns compare).
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seasynth.service.shards import frame_file
from seasynth.service.spec.dataset import DatasetSpec, apply_overrides, read_spec_file, spec_digest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
WIDTH, HEIGHT = 640, 480
REFERENCE_GRID = 4  # 4x4 samples per pixel

# Pinned scenes: overrides on the example spec, and the frame rendered. Seeds, water and cameras are fixed here.
SCENES: dict[str, dict] = {
    "spines-open-water": {
        "seed": 11,
        "terrain.size_m": 1.2,
        "terrain.cells": 48,
        "terrain.relief_m": 0.02,
        "terrain.styles": ["sand"],
        "targets.count": [6, 8],
        "targets.scale": [1.2, 1.4],
        "distractors.count": [0, 0],
        "workspaces.targets": {"min": [-0.5, -0.5, -1.0], "max": [0.5, 0.5, 1.0]},
        "workspaces.look_at": {"min": [-0.3, -0.3, -1.0], "max": [0.3, 0.3, 1.0]},
        "workspaces.camera": {"min": [-0.2, -0.95, 0.06], "max": [0.2, -0.85, 0.1]},
        "water.jerlov": ["3C"],
        "terrain.far_field": False,  # the spines' edges against open water, as the scene's name says
    },
    "wide-fov": {"seed": 12, "camera.hfov_deg": 110.0},
    "turbid-far": {
        "seed": 13,
        "terrain.size_m": 80.0,
        "terrain.cells": 256,
        "targets.scale": [2.5, 3.5],
        "targets.count": [6, 10],
        "distractors.scale": [2.0, 3.0],
        "workspaces.targets": {"min": [-8.0, 10.0, -5.0], "max": [8.0, 30.0, 5.0]},
        "workspaces.distractors": {"min": [-10.0, 10.0, -5.0], "max": [10.0, 30.0, 5.0]},
        "workspaces.look_at": {"min": [-8.0, 10.0, -5.0], "max": [8.0, 30.0, 5.0]},
        "workspaces.camera": {"min": [-1.0, -0.5, 1.5], "max": [1.0, 0.5, 2.5]},
        "water.jerlov": ["9C"],
        "water.beta_jitter": [1.0, 1.0],
    },
    "clear-water": {
        "seed": 14,
        "water.jerlov": [],
        "water.beta_D": {"min": [0, 0, 0], "max": [0, 0, 0]},
        "water.beta_B": {"min": [0, 0, 0], "max": [0, 0, 0]},
        "water.B_inf": {"min": [0.0, 0.1, 0.2], "max": [0.0, 0.1, 0.2]},
    },
    "grazing": {
        "seed": 15,
        "terrain.size_m": 40.0,
        "terrain.cells": 256,
        "workspaces.camera": {"min": [-0.5, -2.0, 0.25], "max": [0.5, -1.8, 0.3]},
        "workspaces.look_at": {"min": [-1.0, 15.0, 0.0], "max": [1.0, 18.0, 0.2]},
        "workspaces.targets": {"min": [-2.0, -1.0, -5.0], "max": [2.0, 6.0, 5.0]},
        "workspaces.distractors": {"min": [-3.0, -1.0, -5.0], "max": [3.0, 10.0, 5.0]},
        "water.jerlov": ["II"],
    },
    "urchins": {"seed": 7},
}
PRESET_NAMES = ("draft", "fast", "default", "high")
JPEG_PRESET = "default"  # rows for outputs.image_format jpeg (--jpeg Q) render with this preset


def variant_specs(spec: DatasetSpec, presets: list[str],
                  jpeg: tuple[int, ...] = ()) -> dict[tuple[str, str], DatasetSpec]:
    """(preset, image) -> the spec rendered for that row: every preset as PNG, then JPEG_PRESET as JPEG at each
    quality in `jpeg` (image "jpeg q95", ...)."""
    out = {(p, "png"): spec.model_copy(update={"quality": p}) for p in presets}
    for q in jpeg:
        o = spec.outputs.model_copy(update={"image_format": "jpeg", "jpeg_quality": q})
        out[(JPEG_PRESET, f"jpeg q{q}")] = spec.model_copy(update={"quality": JPEG_PRESET, "outputs": o})
    return out


def scene_spec(name: str) -> DatasetSpec:
    base = read_spec_file(EXAMPLE)
    overrides = {"frames": 1, "camera.width": WIDTH, "camera.height": HEIGHT, **SCENES[name]}
    return DatasetSpec.model_validate(apply_overrides(base, overrides))


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 100.0 if mse == 0 else min(100.0, 10 * np.log10(255.0**2 / mse))


def hazed_mean(J: np.ndarray, R: np.ndarray, scene, view) -> np.ndarray:
    """Float64 water of the scene's model per sample (the paper's haze, or the physical model's `volume_pixels`),
    averaged in linear light. J: (k, h, w, 3), R: (k, h, w) -> (h, w, 3) float64."""
    from seasynth.worker.frame.formation import haze
    from seasynth.worker.light.volume import camera_depth, pixel_rays, volume_pixels

    water, light = scene.water, scene.light
    if light is not None:
        dirs_world, dirs_cam = pixel_rays(view.K, view.width, view.height, scene.world_from_cam)
        return volume_pixels(J, R, dirs_world, dirs_cam, camera_depth(light, scene.world_from_cam), light)
    acc = np.zeros(J.shape[1:], np.float64)
    for Jk, Rk in zip(J, R):
        Jk = Jk.astype(np.float64)
        acc += Jk if water is None else haze(Jk, Rk, water.beta_D, water.beta_B, water.B_inf, np.float64)
    return acc / len(J)


def majority_ids(ids_hi: np.ndarray, s: int) -> np.ndarray:
    """(H*s, W*s) uint32 ids -> (H, W) uint32: the id covering most of each pixel's s*s samples (ties: the smallest id).

    This is what the reference boxes are made of: each reference box is the tight box of a target's pixels in this
    majority image (ids_hi from the ids pass on an s-times finer grid, one sample at each sub-pixel centre). Terrain
    and open water are both id 0, so they count together as one background id: a pixel whose samples are 7 target,
    5 terrain and 4 water is background (9 against 7), and a 8-8 tie between a target and background goes to the
    background (0 is the smallest id). The frames' own labels sample one id at each pixel centre instead, so the
    label columns measure centre sampling against majority coverage, not a bug in either.
    """
    H, W = ids_hi.shape[0] // s, ids_hi.shape[1] // s
    blocks = ids_hi.reshape(H, s, W, s).transpose(0, 2, 1, 3).reshape(H, W, s * s)
    values = np.unique(blocks)
    counts = np.stack([(blocks == v).sum(axis=2) for v in values], axis=2)
    return values[np.argmax(counts, axis=2)]


def boxes_of(session, view, scene, items, instance) -> dict[int, tuple[int, int, int, int]]:
    from seasynth.worker.frame.labels import tight_boxes

    targets = {p.instance_id for p in scene.objects if p.role == "target"}
    return {i: (b.left, b.top, b.right, b.bottom) for i, b in tight_boxes(instance).items() if i in targets}


@dataclass
class Reference:
    image: np.ndarray  # (h, w, 3) uint8
    boxes: dict[int, tuple[int, int, int, int]]


def reference(session, spec: DatasetSpec) -> Reference:
    from seasynth.worker.frame.function import scene_light
    from seasynth.worker.frame.srgb import encode_srgb8
    from seasynth.worker.render import Sampling, View

    scene = session.scene(spec, 0)
    view = session.view(spec, scene)
    items = session.draw_items(scene)
    J, R = session.renderer.samples(view, items, scene_light(scene), Sampling(msaa=1, supersample=REFERENCE_GRID))
    image = encode_srgb8(hazed_mean(J, R, scene, view))
    s = REFERENCE_GRID
    K = view.K.copy()
    K[:2, :2] *= s
    K[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5  # the same image plane on an s-times finer pixel grid
    hi = View(K=K, width=view.width * s, height=view.height * s, cam_from_world=view.cam_from_world,
              near=view.near, far=view.far)
    ids_hi, _ = session.renderer._ids(hi, items, True, False)
    return Reference(image=image, boxes=boxes_of(session, view, scene, items, majority_ids(ids_hi, s)))


def time_presets(session, specs: dict, repeats: int) -> dict:
    """Median seconds of `frame_files` per row's spec (variant_specs); rows take turns in every round so drift hits
    all alike."""
    for s in specs.values():
        session.frame_files(s, 0)  # warm: shader variants, uploads
    times: dict = {p: [] for p in specs}
    for _ in range(repeats):
        for p, s in specs.items():
            t = time.perf_counter()
            session.frame_files(s, 0)
            times[p].append(time.perf_counter() - t)
    return {p: statistics.median(v) for p, v in times.items()}


def errors(session, s: DatasetSpec, ref: Reference) -> dict:
    """The row's image (spec `s`: its preset and image format) and labels against the reference, and its water
    against float64 on its own samples. A JPEG row's formation_error is None: its image is the PNG row's through
    the codec, whose largest difference from it is codec_max_err."""
    import io

    from PIL import Image

    from seasynth.worker.frame.function import PRESETS, Passes, scene_light
    from seasynth.worker.frame.srgb import encode_srgb8

    preset = s.quality
    files = session.frame_files(s, 0)
    image = np.asarray(Image.open(io.BytesIO(files[frame_file("image", 0, s.outputs.image_suffix)])).convert("RGB"))
    scene = session.scene(s, 0)
    view = session.view(s, scene)
    items = session.draw_items(scene)
    J, R = session.renderer.samples(view, items, scene_light(scene), PRESETS[preset])
    exact = encode_srgb8(hazed_mean(J, R, scene, view))
    res = session.renderer.render(view, items, scene.lighting, scene.water, PRESETS[preset], Passes(ids=True))
    boxes = boxes_of(session, view, scene, items, res.instance)
    # label_error_px: the largest difference of any box edge (pixels) over the targets labelled both here (tight
    # boxes of the pixel-centre ids) and in the reference (tight boxes of majority_ids); label_mismatches: targets
    # labelled in only one of the two (e.g. a target that covers some pixel centre but no pixel's majority).
    common = boxes.keys() & ref.boxes.keys()
    label_err = max((max(abs(a - b) for a, b in zip(boxes[i], ref.boxes[i])) for i in common), default=0)
    diff = np.abs(image.astype(np.int64) - ref.image.astype(np.int64))
    formation = int(np.abs(image.astype(np.int64) - exact.astype(np.int64)).max())
    codec = {}
    if s.outputs.image_format != "png":
        png = s.model_copy(update={"outputs": s.outputs.model_copy(update={"image_format": "png"})})
        lossless = np.asarray(Image.open(io.BytesIO(session.frame_files(png, 0)[frame_file("image", 0)])))
        codec = {"codec_max_err": int(np.abs(image.astype(np.int64) - lossless.astype(np.int64)).max())}
        formation = None
    return {
        "psnr_db": round(psnr_db(image, ref.image), 2),
        "max_abs_err": int(diff.max()),
        "formation_error": formation,
        **codec,
        "label_error_px": int(label_err),
        "label_mismatches": len(boxes.keys() ^ ref.boxes.keys()),
        "labelled_targets": len(boxes),
    }


def run(out: Path, *, scenes, presets, repeats: int, machine: str | None, platform: str,
        jpeg: tuple[int, ...] = ()) -> dict:
    from seasynth.bench.throughput import machine_description
    from seasynth.worker.frame.function import RenderSession

    scenes = scenes or list(SCENES)
    presets = presets or list(PRESET_NAMES)
    for name in scenes:
        if name not in SCENES:
            raise SystemExit(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    for p in presets:
        if p not in PRESET_NAMES:
            raise SystemExit(f"unknown preset {p!r}; known: {', '.join(PRESET_NAMES)}")
    rows = []
    with RenderSession(platform=platform) as session:
        renderer_name = session.renderer_name
        for name in scenes:
            spec = scene_spec(name)
            ref = reference(session, spec)
            specs = variant_specs(spec, presets, tuple(jpeg))
            ms = time_presets(session, specs, repeats)
            for (preset, image), s in specs.items():
                row = {"scene": name, "preset": preset, **({"image": image} if jpeg else {}),
                       "ms_per_frame": round(ms[preset, image] * 1e3, 2), **errors(session, s, ref)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    result = {"machine": machine or machine_description(), "gl_renderer": renderer_name, "resolution": [WIDTH, HEIGHT],
              "reference": f"{REFERENCE_GRID}x{REFERENCE_GRID} samples, float64 water per sample", "repeats": repeats,
              # Each scene's whole spec, hashed: a table is comparable with another only where these agree.
              "scene_spec_sha256": {name: spec_digest(scene_spec(name)) for name in scenes}, "rows": rows}
    write_results(out, "accuracy", result, format_table(result), lambda path: plot(result, path))
    return result


def write_results(out: Path, stem: str, result: dict, table: str, draw) -> None:
    """A bench's committed trio: STEM.json (result), STEM.md (table, also printed) and STEM.png (draw(path))."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / f"{stem}.md").write_text(table + "\n")
    draw(out / f"{stem}.png")
    print(table)


def format_table(result: dict) -> str:
    keys = ("ms_per_frame", "psnr_db", "max_abs_err", "formation_error", "label_error_px", "label_mismatches")
    images = any("image" in r for r in result["rows"])  # a run with JPEG rows (--jpeg) has an image column
    if images:
        keys = (*keys, "codec_max_err")
    lines = [
        f"# Accuracy against time ({result['resolution'][0]}x{result['resolution'][1]})",
        "",
        f"machine: {result['machine']}  ",
        f"GL renderer: {result['gl_renderer']}  ",
        f"reference: {result['reference']}  ",
        f"ms_per_frame: median of {result['repeats']} repeats",
        "",
        "| scene | preset | " + "image | " * images + " | ".join(keys) + " |",
        "|---|---|" + "---|" * images + "---|" * len(keys),
    ]
    for r in result["rows"]:
        cells = [str(r.get(k, "")) if r.get(k) is not None else "-" for k in keys]
        image = f"{r['image']} | " if images else ""
        lines.append(f"| {r['scene']} | {r['preset']} | {image}" + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    markers = {"draft": "o", "fast": "D", "default": "s", "high": "^"}
    scenes = sorted({r["scene"] for r in result["rows"]})
    colours = dict(zip(scenes, plt.cm.tab10.colors))
    for r in result["rows"]:
        jpeg = r.get("image", "png") != "png"
        ax.scatter(r["ms_per_frame"], r["psnr_db"], marker="x" if jpeg else markers.get(r["preset"], "x"),
                   color=colours[r["scene"]])
    for s in scenes:  # the presets' line (JPEG rows are crosses off it)
        pts = sorted((r["ms_per_frame"], r["psnr_db"]) for r in result["rows"]
                     if r["scene"] == s and r.get("image", "png") == "png")
        ax.plot(*zip(*pts), color=colours[s], lw=0.8, label=s)
    for p, m in markers.items():
        ax.scatter([], [], marker=m, color="grey", label=p)
    if any(r.get("image", "png") != "png" for r in result["rows"]):
        ax.scatter([], [], marker="x", color="grey", label="default, JPEG")
    ax.axhline(40, color="grey", ls=":", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (median)")
    ax.set_ylabel("PSNR vs 16-sample float64 reference (dB)")
    ax.set_title(f"Error against time, {result['gl_renderer'][:40]}", fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
