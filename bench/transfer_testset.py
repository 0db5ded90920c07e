"""The transfer bench's held-out test set: scenes no training spec can draw (bench/transfer_recipe.py says why),
path traced with Mitsuba 3 and labelled from exact geometry, written as a COCO folder.

Per image: the scene of group k's spec (seed test.seed_first + k) at frame i, its procedural meshes, terrain and
texture sets taken from held-out variants; rendered as two independent halves of the group's samples per pixel (test.spp unless it says), the
image the 8-bit sRGB of their mean, and the halves' PSNR to each other its residual noise (the mean's own error is
about 6 dB below it); labels are the tight boxes of each target's pixels in the path tracer's own
instance ids at pixel centres (pathtracer.render_ids). A box whose object does not stand out from its surroundings
in the image (contrast below test.min_contrast: an urchin in the dark beyond the lamps' beams, or lost in the
veiling light) is kept as an ignored region (COCO iscrowd 1): finding it is not a false positive, missing it is not
a miss, as an annotator would not have labelled it.

Layout of OUT: images/test/{group}-{i:05d}.png, records/{group}-{i:05d}.json (seeds, digests, noise; an image with
its record of the same test recipe is complete, so a rerun resumes), annotations/instances_test.json (COCO, as `seasynth export` writes).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from seasynth.bench.transfer_recipe import HELD_OUT_FIRST_VARIANT, Recipe, held_out_specs
from seasynth.service.seeds import frame_rng
from seasynth.service.spec.dataset import DatasetSpec

SPLIT = "test"
RING_PX = 3  # the surroundings an object's contrast is measured against: pixels within this of its box


def held_out_scene(session, spec: DatasetSpec, index: int):
    """Frame `index`'s scene of `spec` with every procedural variant v drawn as HELD_OUT_FIRST_VARIANT + v, and
    every procedural surface textured with the texture set of that held-out variant (not v mod
    materials.variants). The draws are sample_scene's own, from frame_rng(spec.seed, index)."""
    from seasynth.worker.scene.assets.terrain import with_material
    from seasynth.worker.scene.materials import (
        ASSET_FAMILY,
        STYLE_FAMILY,
        material_key,
        procedural_material,
        terrain_tile_m,
    )
    from seasynth.worker.scene.sample import sample_scene

    m = spec.materials

    def texture(family: str, variant: int, mapping: str):
        return procedural_material(family, variant, m.texture_px, mapping, float(m.anisotropy)) if m.procedural \
            else None

    def asset_for(ref, variant):
        return session.asset_for(ref, None if variant is None else HELD_OUT_FIRST_VARIANT + variant)

    def terrain_for(spec: DatasetSpec, rng: np.random.Generator):
        t = spec.terrain
        if t.mesh is not None or t.texture is not None:
            raise ValueError("held-out scenes draw built-in terrains: terrain.mesh and terrain.texture must be unset")
        style = t.styles[rng.integers(len(t.styles))]  # the draws of RenderSession.terrain_for, in its order
        variant = HELD_OUT_FIRST_VARIANT + int(rng.integers(t.variants))
        terrain = session.variants.terrain(style, variant, t.size_m, t.cells, t.relief_m)
        material = texture(STYLE_FAMILY[style], variant, "uv")
        if material is None:
            return terrain
        return with_material(terrain, material, material_key(material), False, terrain_tile_m(material, spec),
                             t.anti_tiling)

    scene = sample_scene(spec, frame_rng(spec.seed, index), asset_for, terrain_for)
    objects = []
    for p in scene.objects:
        if p.variant is not None:
            held = HELD_OUT_FIRST_VARIANT + p.variant
            kind = p.asset.key.split("/")[1]
            p = dataclasses.replace(p, variant=held, material=texture(ASSET_FAMILY[kind], held, "triplanar"))
        objects.append(p)
    return dataclasses.replace(scene, objects=tuple(objects))


def tight_boxes(ids: np.ndarray, wanted: set[int]) -> dict[int, tuple[int, int, int, int]]:
    """{instance id: (left, top, right, bottom)} inclusive 0-based pixel box of each wanted id's pixels in
    ids (h, w) integer instance ids; ids without a pixel are left out."""
    out = {}
    present = np.unique(ids)
    for i in sorted(wanted & {int(x) for x in present}):
        rows = np.flatnonzero((ids == i).any(axis=1))
        cols = np.flatnonzero((ids == i).any(axis=0))
        out[i] = (int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1]))
    return out


def contrast(image: np.ndarray, ids: np.ndarray, instance: int, box: tuple[int, int, int, int],
             ring_px: int = RING_PX) -> float:
    """How far an object stands out: the largest per-channel difference, in 8-bit sRGB codes, between the mean of
    its pixels and the mean of the other pixels within ring_px of its box. image (h, w, 3) uint8; ids (h, w)."""
    h, w = ids.shape
    left, top, right, bottom = box
    window = (slice(max(top - ring_px, 0), min(bottom + ring_px + 1, h)),
              slice(max(left - ring_px, 0), min(right + ring_px + 1, w)))
    mine = ids[window] == instance
    pixels = image[window].astype(np.float64)
    if mine.all():
        return 0.0  # nothing around it in view to stand out from
    return float(np.abs(pixels[mine].mean(axis=0) - pixels[~mine].mean(axis=0)).max())


def render_frame(session, spec: DatasetSpec, index: int, recipe: Recipe, spp: int, variant: str) -> dict:
    """One test image: {'image': (h, w, 3) uint8 sRGB, 'boxes': [(l, t, r, b)], 'contrast': [sRGB codes] (one per
    box), 'noise_db', 'scene_sha256', 'seconds', 'variants'}."""
    from seasynth.bench import pathtracer
    from seasynth.bench.accuracy import psnr_db
    from seasynth.bench.fidelity_scene import exported_scene
    from seasynth.bench.reference import scene_digest
    from seasynth.worker.frame.srgb import encode_srgb8

    scene = held_out_scene(session, spec, index)
    pt = exported_scene(session, spec, scene)
    t0 = time.perf_counter()
    halves = pathtracer.render_seeds(pt, spp, (0, 1), max_depth=recipe.test.max_depth, variant=variant,
                                     lamp_housing_m=recipe.test.lamp_housing_m, exact_nee=recipe.test.exact_nee)
    ids = pathtracer.render_ids(pt, variant=variant)
    seconds = time.perf_counter() - t0
    targets = {p.instance_id for p in scene.objects if p.role == "target"}
    image = encode_srgb8((halves[0] + halves[1]) / 2)
    boxes = tight_boxes(ids, targets)
    return {"image": image, "boxes": list(boxes.values()),
            "contrast": [round(contrast(image, ids, i, b), 2) for i, b in boxes.items()],
            "noise_db": float(psnr_db(encode_srgb8(halves[0]), encode_srgb8(halves[1]))),
            "scene_sha256": scene_digest(pt), "seconds": seconds,
            "variants": sorted({p.variant for p in scene.objects if p.variant is not None})}


def build(recipe: Recipe, out: Path, variant: str, platform: str = "egl", shard: tuple[int, int] = (0, 1),
          log=print) -> dict | None:
    """Render the recipe's test set into `out` (resuming complete images), then write its COCO json; returns the
    summary {'images', 'boxes', 'noise_db_min', 'noise_db_median', 'seconds', 'records'}. shard (k, n) other than
    (0, 1): render only the images whose place in the set is k mod n (one process per GPU), write no json and
    return None."""
    from PIL import Image

    from seasynth.worker.frame.function import RenderSession

    images_dir, records_dir = out / "images" / SPLIT, out / "records"
    digest = testset_digest(recipe)
    images_dir.mkdir(parents=True, exist_ok=True)
    records_dir.mkdir(parents=True, exist_ok=True)
    with RenderSession(platform=platform) as session:
        place = -1
        for group, spec in held_out_specs(recipe):
            for i in range(group.frames):
                place += 1
                name = f"{group.name}-{i:05d}"
                record_path = records_dir / f"{name}.json"
                if place % shard[1] != shard[0] or _complete(record_path, images_dir / f"{name}.png", digest):
                    continue
                spp = group.spp or recipe.test.spp
                r = render_frame(session, spec, i, recipe, spp, variant)
                png = images_dir / f"{name}.png"
                Image.fromarray(r["image"]).save(png, optimize=False)
                record = {"file_name": png.name, "test_sha256": digest, "group": group.name, "dataset_seed": spec.seed, "frame": i,
                          "boxes": r["boxes"], "contrast": r["contrast"], "noise_db": round(r["noise_db"], 2), "spp_per_half": spp,
                          "variant": variant, "seconds": round(r["seconds"], 2), "scene_sha256": r["scene_sha256"],
                          "png_sha256": hashlib.sha256(png.read_bytes()).hexdigest(),
                          "held_out_variants": r["variants"]}
                record_path.write_text(json.dumps(record) + "\n")
                log(json.dumps({k: record[k] for k in ("file_name", "noise_db", "seconds")}
                               | {"boxes": len(record["boxes"])}))
        class_name = spec.targets[0].class_name  # the recipes' test sets have one class
    if shard != (0, 1):
        return None
    records = [json.loads((records_dir / f"{g.name}-{i:05d}.json").read_text())
               for g in recipe.test.groups for i in range(g.frames)]
    write_coco(out, records, class_name, recipe.width, recipe.height, recipe.test.min_contrast)
    noise = sorted(r["noise_db"] for r in records)
    return {"images": len(records), "boxes": sum(len(r["boxes"]) for r in records),
            "boxes_visible": sum(c >= recipe.test.min_contrast for r in records for c in r["contrast"]),
            "noise_db_min": noise[0], "noise_db_median": noise[len(noise) // 2],
            "seconds": round(sum(r["seconds"] for r in records), 1), "records": records}


def testset_digest(recipe: Recipe) -> str:
    """sha256 of what makes the test set's images and boxes: base spec file, resolution and the recipe's test
    section (but min_contrast)."""
    from seasynth.bench.transfer_recipe import REPO

    # min_contrast is a threshold on what was rendered: no new render; exact_nee off is what test sets were before it
    test = recipe.test.model_dump(exclude={"min_contrast"} | (set() if recipe.test.exact_nee else {"exact_nee"}))
    text = json.dumps([(REPO / recipe.base_spec).read_text(), recipe.width, recipe.height, test], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _complete(record: Path, png: Path, digest: str) -> bool:
    return record.exists() and png.exists() and json.loads(record.read_text()).get("test_sha256") == digest


def write_coco(out: Path, records: list[dict], class_name: str, width: int, height: int,
               min_contrast: float) -> Path:
    """annotations/instances_test.json of the records: image ids 0.. in record order, boxes as coco_bbox, those of
    contrast below min_contrast as ignored regions (iscrowd 1)."""
    from seasynth.worker.export.coco import coco_bbox

    images, annotations = [], []
    for image_id, r in enumerate(records):
        images.append({"id": image_id, "file_name": r["file_name"], "width": width, "height": height})
        for box, c in zip(r["boxes"], r["contrast"]):
            bbox = coco_bbox(tuple(box))
            annotations.append({"id": len(annotations) + 1, "image_id": image_id, "category_id": 1, "bbox": bbox,
                                "area": bbox[2] * bbox[3], "iscrowd": int(c < min_contrast), "contrast": c})
    path = out / "annotations" / f"instances_{SPLIT}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"images": images, "annotations": annotations,
                                "categories": [{"id": 1, "name": class_name}]}) + "\n")
    return path
