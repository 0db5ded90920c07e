"""The transfer bench's metrics, as the paper reports them: mAP50 and mAP50-95 from pycocotools (COCOeval, bbox,
all areas, 100 detections per image), and precision and recall at the score threshold that maximises F1, from
COCOeval's own matching at IoU 0.5."""

from __future__ import annotations

import contextlib
import io

import numpy as np


def evaluate(gt: dict, detections: list[dict]) -> dict:
    """{'map50', 'map50_95', 'precision', 'recall', 'f1', 'score_threshold'} of `detections` (COCO results:
    image_id, category_id, bbox [x, y, w, h] px, score) against the COCO ground truth dict `gt`.

    No detections at all scores 0 everywhere (COCOeval refuses an empty result list)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    if not detections:
        return {"map50": 0.0, "map50_95": 0.0, "precision": 0.0, "recall": 0.0, "f1": 0.0, "score_threshold": None}
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints its progress
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(detections)
        ev = COCOeval(coco_gt, coco_dt, "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    out = {"map50": _nonneg(ev.stats[1]), "map50_95": _nonneg(ev.stats[0])}
    return out | best_f1(ev)


def _nonneg(x: float) -> float:
    return max(float(x), 0.0)  # COCOeval writes -1 where there is no ground truth


def best_f1(ev) -> dict:
    """Precision, recall and F1 at the score threshold maximising F1, from an evaluated COCOeval's matches at
    IoU 0.5 (area 'all', the largest maxDets): every detection kept by COCOeval is a true positive if matched,
    else a false positive; ignored ones count as neither."""
    t = int(np.argmin(np.abs(ev.params.iouThrs - 0.5)))
    max_det = ev.params.maxDets[-1]
    scores, tp, npos = [], [], 0
    for e in ev.evalImgs:
        if e is None or e["aRng"] != ev.params.areaRng[0] or e["maxDet"] != max_det:
            continue
        npos += int(np.count_nonzero(~np.asarray(e["gtIgnore"], dtype=bool)))
        keep = ~np.asarray(e["dtIgnore"], dtype=bool)[t]
        scores.append(np.asarray(e["dtScores"], dtype=np.float64)[keep])
        tp.append(np.asarray(e["dtMatches"])[t][keep] > 0)
    if npos == 0 or not scores:
        return {"precision": 0.0, "recall": 0.0, "f1": 0.0, "score_threshold": None}
    return f1_point(np.concatenate(scores), np.concatenate(tp), npos)


def f1_point(scores: np.ndarray, tp: np.ndarray, npos: int) -> dict:
    """Precision, recall, F1 and score threshold of the best F1 over thresholds at each detection's score.

    scores (n,) float64; tp (n,) bool (the detection matched a ground truth); npos: ground truth boxes."""
    if len(scores) == 0:
        return {"precision": 0.0, "recall": 0.0, "f1": 0.0, "score_threshold": None}
    order = np.argsort(-scores, kind="stable")
    s, hits = scores[order], tp[order].astype(np.float64)
    ctp = np.cumsum(hits)
    n = np.arange(1, len(s) + 1)
    last = np.r_[s[1:] != s[:-1], True]  # a threshold keeps every detection of equal score
    precision, recall = (ctp / n)[last], (ctp / npos)[last]
    f1 = np.where(precision + recall > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-12), 0.0)
    k = int(np.argmax(f1))
    return {"precision": float(precision[k]), "recall": float(recall[k]), "f1": float(f1[k]),
            "score_threshold": float(s[last][k])}
