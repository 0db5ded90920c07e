"""The small local datasets and their COCO and YOLO exports that the export tests read (module-scoped fixtures)."""

from __future__ import annotations

from pathlib import Path

import pytest
from local_datasets import generate_variants

from seasynth.worker.export import plan_export, run_export

SMALL = {"camera.width": 64, "camera.height": 48, "frames": 8}
WITH_MASKS = {"outputs.instance": True}
FRACTIONS = (0.5, 0.25, 0.25)
SPLIT = "0.5,0.25,0.25"


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    """The same frames three ways: with instance/ by one worker, by two workers, and without instance/."""
    return generate_variants(tmp_path_factory.mktemp("datasets"), SMALL,
                             {"masks": (WITH_MASKS, 1), "masks2": (WITH_MASKS, 2), "plain": ({}, 1)})


@pytest.fixture(scope="module")
def coco(datasets, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("coco") / "out"
    run_export(plan_export(datasets["masks"], "coco", FRACTIONS), out)
    return out


@pytest.fixture(scope="module")
def yolo(datasets, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("yolo") / "out"
    run_export(plan_export(datasets["masks"], "yolo", FRACTIONS), out)
    return out
