"""The transfer bench's detector: torchvision's Faster R-CNN (MobileNetV3-Large FPN, 320 px) from random
initialisation (nothing downloaded), trained on a `seasynth export --format coco` folder's train split with the
recipe's fixed schedule and augmentation, and its detections on a COCO folder as COCO results.

Needs torch and torchvision (not seasynth dependencies). Images are read from the export's PNGs as batches are
drawn (threads decode the next batch while the GPU trains on this one), so memory stays flat in the dataset's
size; augmentation runs on the training device."""

from __future__ import annotations

import json
import math
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image

from seasynth.bench.transfer_recipe import Training

LOADER_THREADS = 4  # PNG decoding threads (PIL releases the GIL while it inflates)
MODEL = "torchvision fasterrcnn_mobilenet_v3_large_320_fpn, weights=None, weights_backbone=None"


def read_coco(folder: Path, split: str) -> tuple[dict, list[tuple[Path, np.ndarray]]]:
    """(the COCO dict, [(image path, boxes (n, 4) float32 x1 y1 x2 y2 px pixel-edge)]) of a COCO folder's split,
    category 1 only (the target class); images without boxes kept."""
    coco = json.loads((folder / "annotations" / f"instances_{split}.json").read_text())
    boxes: dict[int, list] = {}
    for a in coco["annotations"]:
        if a["category_id"] == 1:
            x, y, w, h = a["bbox"]
            boxes.setdefault(a["image_id"], []).append([x, y, x + w, y + h])
    items = [(folder / "images" / split / im["file_name"],
              np.asarray(boxes.get(im["id"], []), dtype=np.float32).reshape(-1, 4)) for im in coco["images"]]
    return coco, items


def _load(path: Path) -> np.ndarray:
    """(h, w, 3) uint8 RGB."""
    return np.array(Image.open(path).convert("RGB"))  # writable: torch warns on a read-only array


def augment(img, boxes: np.ndarray, rng: np.random.Generator, t: Training):
    """(image, boxes (n, 4) float32 x1 y1 x2 y2 px): img a (3, h, w) float tensor in [0, 1] (on any device), flipped
    horizontally with probability t.hflip (boxes mirrored), its brightness and contrast each scaled by a factor in
    1 +- t.jitter (contrast about the image's mean), clipped to [0, 1]."""
    if rng.random() < t.hflip:
        w = img.shape[2]
        img = img.flip(2)
        boxes = np.stack([w - boxes[:, 2], boxes[:, 1], w - boxes[:, 0], boxes[:, 3]], axis=1)
    brightness, contrast = (float(x) for x in rng.uniform(1 - t.jitter, 1 + t.jitter, size=2))
    mean = img.mean()
    return ((img - mean) * contrast + mean * brightness).clamp(0.0, 1.0), boxes.astype(np.float32)


def lr_factor(step: int, t: Training) -> float:
    """The learning rate's factor at `step` (0-based): linear warm-up to 1, then a cosine to 0 at t.steps."""
    if step < t.warmup_steps:
        return (step + 1) / t.warmup_steps
    span = max(t.steps - t.warmup_steps, 1)
    return 0.5 * (1.0 + math.cos(math.pi * (step - t.warmup_steps) / span))


def build_model(t: Training):
    from torchvision.models.detection import fasterrcnn_mobilenet_v3_large_320_fpn

    return fasterrcnn_mobilenet_v3_large_320_fpn(weights=None, weights_backbone=None, num_classes=2,
                                                 box_score_thresh=t.score_threshold, box_detections_per_img=100,
                                                 min_size=t.min_size, max_size=t.max_size)


def train(export: Path, t: Training, seed: int, device: str, log=print):
    """(the trained model, {'model', 'train_images', 'seconds', 'loss_first', 'loss_last', 'loss_per_twentieth'
    (the mean loss of each twentieth of the steps)}) after t.steps steps of t.batch images from the export's train
    split; batches are epochs of a permutation drawn from `seed`."""
    import torch

    _, items = read_coco(export, "train")
    if not items:
        raise ValueError(f"{export}: the train split has no images")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = build_model(t).to(device).train()
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.SGD(params, lr=t.lr, momentum=t.momentum, weight_decay=t.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, t))
    order: list[int] = []

    def next_batch() -> list[int]:
        while len(order) < t.batch:
            order.extend(rng.permutation(len(items)).tolist())
        picked = order[:t.batch]
        del order[:t.batch]
        return picked

    losses = []
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=LOADER_THREADS) as pool:
        def submit():  # the batch after this one decodes while this one trains
            return [(pool.submit(_load, items[i][0]), items[i][1]) for i in next_batch()]

        pending = submit()
        for step in range(t.steps):
            batch, pending = pending, (submit() if step + 1 < t.steps else [])
            images, targets = [], []
            for future, b in batch:
                rgb = torch.from_numpy(future.result()).to(device).permute(2, 0, 1).float() / 255.0
                img, b = augment(rgb, b, rng, t)
                images.append(img)
                targets.append({"boxes": torch.from_numpy(b).to(device),
                                "labels": torch.ones(len(b), dtype=torch.int64, device=device)})
            loss = sum(model(images, targets).values())
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 10.0)
            opt.step()
            sched.step()
            losses.append(loss.item())
            if (step + 1) % max(t.steps // 10, 1) == 0:
                log(json.dumps({"step": step + 1, "loss": round(float(np.mean(losses[-50:])), 4)}))
    window = max(min(50, t.steps // 4), 1)
    curve = [round(float(np.mean(part)), 4) for part in np.array_split(np.asarray(losses), min(20, len(losses)))]
    return model, {"model": MODEL, "train_images": len(items), "seconds": round(time.perf_counter() - t0, 1),
                   "loss_first": round(float(np.mean(losses[:window])), 4),
                   "loss_last": round(float(np.mean(losses[-window:])), 4), "loss_per_twentieth": curve}


def detect(model, folder: Path, split: str, device: str, batch: int = 16) -> list[dict]:
    """COCO results (image_id, category_id 1, bbox [x, y, w, h] px, score) of `model` on a COCO folder's split."""
    import torch

    coco, items = read_coco(folder, split)
    model.eval()
    out = []
    with torch.no_grad():
        for first in range(0, len(items), batch):
            chunk = coco["images"][first:first + batch]
            images = [torch.from_numpy(_load(p).astype(np.float32) / 255.0).permute(2, 0, 1).to(device)
                      for p, _ in items[first:first + batch]]
            for im, pred in zip(chunk, model(images)):
                for (x1, y1, x2, y2), score in zip(pred["boxes"].cpu().tolist(), pred["scores"].cpu().tolist()):
                    out.append({"image_id": im["id"], "category_id": 1, "score": round(score, 5),
                                "bbox": [round(x1, 2), round(y1, 2), round(x2 - x1, 2), round(y2 - y1, 2)]})
    return out
