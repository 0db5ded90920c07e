"""The transfer bench's report: the result record, its table (ours beside the paper's) and the picture of test
images with ground truth and predictions."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

METRICS = ("precision", "recall", "map50", "map50_95")
TILE_WIDTH = 400  # pixels a test image takes in the picture, at most
NAMES = {"precision": "P", "recall": "R", "map50": "mAP50", "map50_95": "mAP50-95"}


def mean_spread(values: list[float]) -> dict:
    """{'mean', 'std' (sample standard deviation; 0 for one value), 'n'}."""
    return {"mean": round(statistics.fmean(values), 4),
            "std": round(statistics.stdev(values), 4) if len(values) > 1 else 0.0, "n": len(values)}


def summarise(recipe, digest: str, rows, runs: dict, testset: dict, paper: dict, machine: str) -> dict:
    """The result record: recipe and its sha256, the test set (counts, noise, each image's digests), and per row
    each replicate's scores and the mean and spread of each metric."""
    out_rows = []
    for row in rows:
        reps = [runs[(row.name, r)]["scores"] for r in range(len(recipe.training.dataset_seeds))]
        out_rows.append({"name": row.name, "overrides": row.overrides, "frames": row.size * recipe.training.frames_1x,
                         **{k: mean_spread([s[k] for s in reps]) for k in METRICS},
                         "paper": paper.get(row.name), "replicates": reps})
    first = out_rows[0]["replicates"][0]
    groups: dict[str, int] = {}
    for r in testset["records"]:
        groups[r["group"]] = groups.get(r["group"], 0) + 1
    return {
        "machine": machine, "torch": first["torch"], "torchvision": first["torchvision"], "device": first["device"],
        "recipe": recipe.model_dump(), "recipe_sha256": digest,
        "testset": {"images": testset["images"], "boxes": testset["boxes"],
                    "boxes_visible": testset["boxes_visible"], "groups": groups,
                    "noise_db_min": testset["noise_db_min"], "noise_db_median": testset["noise_db_median"],
                    "path_tracer_seconds": testset["seconds"],
                    "images_sha256": [{k: r[k] for k in ("file_name", "scene_sha256", "png_sha256", "noise_db")}
                                      for r in testset["records"]]},
        "rows": out_rows,
    }


def format_table(result: dict) -> str:
    r, t = result["recipe"], result["recipe"]["training"]
    ts = result["testset"]
    n = len(t["dataset_seeds"])
    lines = [
        f"# Transfer: trained on seasynth, tested on path-traced held-out scenes ({r['width']}x{r['height']})", "",
        "The test images are NOT real photographs: they are a volumetric path tracer (Mitsuba 3) of scenes with seeds, "
        "meshes and textures no training spec can draw (bench/transfer_recipe.py).  ",
        f"machine: {result['machine']}; {result['device']}; torch {result['torch']}, torchvision "
        f"{result['torchvision']}  ",
        f"test set: {ts['images']} images, {ts['boxes']} boxes ({ts['boxes_visible']} standing out from their "
        f"surroundings by {r['test']['min_contrast']} sRGB codes or more; the rest are ignored regions) in groups "
        + ", ".join(f"{k} {v}" for k, v in ts["groups"].items())
        + f"; {r['test']['spp']} spp x 2 halves; halves' PSNR min {ts['noise_db_min']} dB, median "
        f"{ts['noise_db_median']} dB  ",
        f"detector: Faster R-CNN MobileNetV3-Large FPN 320 from random init, images resized to a short side of "
        f"{t['min_size']} (long side at most {t['max_size']}); {t['steps']} steps of {t['batch']}, SGD "
        f"lr {t['lr']} (warm-up {t['warmup_steps']}, cosine), flip {t['hflip']}, jitter {t['jitter']}; {n} "
        "replicates per row (dataset seed and detector seed), mean +- sample std  ",
        "P and R at the score threshold maximising F1 (IoU 0.5); mAP from pycocotools  ",
        f"recipe sha256 {result['recipe_sha256'][:16]}", "",
        "| row | overrides | frames | " + " | ".join(NAMES[k] for k in METRICS) + " | paper YOLOv9 | paper DETR |",
        "|---|---|---|" + "---|" * len(METRICS) + "---|---|",
    ]
    for row in result["rows"]:
        paper = row["paper"] or {}
        cells = [f"{row[k]['mean']:.3f} +- {row[k]['std']:.3f}" for k in METRICS]
        ref = [" / ".join(f"{v:.3f}" for v in paper[m]) if m in paper else "-" for m in ("YOLOv9", "DETR")]
        lines.append(f"| {row['name']} | `{json.dumps(row['overrides'])}` | {row['frames']} | " + " | ".join(cells)
                     + " | " + " | ".join(ref) + " |")
    lines += ["", "paper columns: P / R / mAP50 / mAP50-95 on real SeaClear images (Tables II and III), a different "
              "test domain and different detectors: side by side, not comparable number for number"]
    return "\n".join(lines)


def picture(testset: Path, detections: list[dict], row: str, path: Path, count: int = 8) -> None:
    """`count` test images spread over the set: ground truth green (ignored regions yellow), the row's first
    replicate's detections with score >= 0.5 red."""
    from PIL import Image, ImageDraw

    coco = json.loads((testset / "annotations" / "instances_test.json").read_text())
    chosen = coco["images"][:: max(len(coco["images"]) // count, 1)][:count]
    tiles = []
    for im in chosen:
        tile = Image.open(testset / "images" / "test" / im["file_name"]).convert("RGB")
        f = min(1.0, TILE_WIDTH / tile.width)  # the committed picture stays small; boxes drawn after scaling
        tile = tile.resize((round(tile.width * f), round(tile.height * f)), Image.BILINEAR)
        draw = ImageDraw.Draw(tile)

        def box(bbox, colour, draw=draw, f=f):
            x, y, w, h = (v * f for v in bbox)
            draw.rectangle([x, y, x + w, y + h], outline=colour)

        for a in coco["annotations"]:
            if a["image_id"] == im["id"]:
                box(a["bbox"], (255, 255, 0) if a["iscrowd"] else (0, 255, 0))
        for d in detections:
            if d["image_id"] == im["id"] and d["score"] >= 0.5:
                box(d["bbox"], (255, 0, 0))
        draw.text((2, 2), f"{im['file_name']} ({row})", fill=(255, 255, 255))
        tiles.append(tile)
    w, h = tiles[0].size
    cols = min(4, len(tiles))
    sheet = Image.new("RGB", (cols * w, -(-len(tiles) // cols) * h), "white")
    for i, tile in enumerate(tiles):
        sheet.paste(tile, ((i % cols) * w, (i // cols) * h))
    sheet.save(path)
