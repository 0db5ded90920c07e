"""A detector actually trains on an export: torchvision's Faster R-CNN (MobileNetV3-Large FPN, 320 px), initialised at
random (no weights downloaded), trained for a few hundred steps on a `seasynth export --format coco` folder's train
split; the loss per window of steps shows it learning.

    python -m seasynth.bench.train_detector COCO_EXPORT --out DIR [--steps 300] [--batch 4] [--device cuda]

Needs torch and torchvision (not a dependency of seasynth: install them where you train). Reads only the export's
files (json and PNGs), as a user's training script would.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
from PIL import Image

WINDOW = 25  # steps per row of the loss table


def load_split(export: Path, split: str = "train"):
    """[(image (3, h, w) float tensor in [0, 1], target dict)] of a COCO export's split; frames without boxes kept."""
    import torch

    coco = json.loads((export / "annotations" / f"instances_{split}.json").read_text())
    by_image: dict[int, list] = {}
    for a in coco["annotations"]:
        by_image.setdefault(a["image_id"], []).append(a)
    items = []
    for im in coco["images"]:
        rgb = np.asarray(Image.open(export / "images" / split / im["file_name"]).convert("RGB"), dtype=np.float32)
        anns = by_image.get(im["id"], [])
        boxes = [[x, y, x + w, y + h] for x, y, w, h in (a["bbox"] for a in anns)]
        items.append((torch.from_numpy(rgb / 255.0).permute(2, 0, 1).contiguous(), {
            "boxes": torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4),
            "labels": torch.tensor([a["category_id"] for a in anns], dtype=torch.int64),
        }))
    return items, len(coco["categories"])


def train(export: Path, steps: int, batch: int, device: str, seed: int = 0) -> dict:
    import torch
    import torchvision
    from torchvision.models.detection import fasterrcnn_mobilenet_v3_large_320_fpn

    torch.manual_seed(seed)
    items, classes = load_split(export)
    if not items:
        raise SystemExit(f"{export}: the train split has no images")
    model = fasterrcnn_mobilenet_v3_large_320_fpn(weights=None, weights_backbone=None, num_classes=classes + 1)
    model.to(device).train()
    opt = torch.optim.SGD(model.parameters(), lr=0.02, momentum=0.9, weight_decay=1e-4)
    rng = np.random.default_rng(seed)
    losses, parts_log = [], []
    t0 = time.perf_counter()
    for _ in range(steps):
        pick = rng.choice(len(items), size=min(batch, len(items)), replace=False)
        images = [items[i][0].to(device) for i in pick]
        targets = [{k: v.to(device) for k, v in items[i][1].items()} for i in pick]
        parts = model(images, targets)
        loss = sum(parts.values())
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        losses.append(float(loss))
        parts_log.append({k: float(v) for k, v in parts.items()})
    seconds = time.perf_counter() - t0
    windows = [losses[i:i + WINDOW] for i in range(0, len(losses), WINDOW)]
    return {
        "model": "torchvision fasterrcnn_mobilenet_v3_large_320_fpn, weights=None, weights_backbone=None",
        "torch": torch.__version__, "torchvision": torchvision.__version__, "device": device,
        "device_name": torch.cuda.get_device_name(0) if device.startswith("cuda") else platform.processor(),
        "export": str(export), "train_images": len(items), "classes": classes, "steps": steps, "batch": batch,
        "seconds": round(seconds, 1), "optimizer": "SGD lr 0.02 momentum 0.9 wd 1e-4, grad norm clipped at 10",
        "loss_per_window": [round(statistics.mean(w), 4) for w in windows],
        "parts_last_window": {k: round(statistics.mean(p[k] for p in parts_log[-WINDOW:]), 4)
                              for k in parts_log[-1]},
    }


def format_table(r: dict) -> str:
    first, last = r["loss_per_window"][0], r["loss_per_window"][-1]
    lines = [
        "# A detector trains on a seasynth COCO export", "",
        f"model: {r['model']}  ", f"torch {r['torch']}, torchvision {r['torchvision']}, on {r['device_name']}  ",
        f"data: {r['train_images']} train images, {r['classes']} class(es); {r['steps']} steps of {r['batch']} "
        f"images in {r['seconds']} s; {r['optimizer']}", "",
        f"mean loss of the first {WINDOW} steps {first:.3f}, of the last {WINDOW} {last:.3f} "
        f"({'down' if last < first else 'NOT down'} {100 * (1 - last / first):.0f}%)", "",
        "| steps | mean loss |", "|---|---|",
        *[f"| {i * WINDOW + 1}-{min((i + 1) * WINDOW, r['steps'])} | {v:.4f} |"
          for i, v in enumerate(r["loss_per_window"])],
        "", "last window's parts: " + ", ".join(f"{k} {v:.4f}" for k, v in r["parts_last_window"].items()),
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("export", type=Path, help="a `seasynth export --format coco` folder")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--device", default="cuda")
    a = p.parse_args(argv)
    r = train(a.export, a.steps, a.batch, a.device)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "train.json").write_text(json.dumps(r, indent=1) + "\n")
    (a.out / "train.md").write_text(format_table(r) + "\n")
    print(format_table(r))


if __name__ == "__main__":
    main()
