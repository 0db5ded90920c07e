"""The transfer bench's recipe (bench/recipes/transfer*.json): the held-out path-traced test set, the training
recipe and the ablation rows as spec overrides; and what makes the test set disjoint from every training set.

Disjointness is by construction, not by luck:
- seeds: every test group's dataset seed lies in [test.seed_first, test.seed_first + groups) and every training
  dataset seed below test.seed_first, so no (dataset seed, frame index) pair, hence no frame generator, is shared;
- assets and terrains: a valid spec draws procedural variants in [0, MAX_VARIANTS) (service.spec.scene); the test
  scenes take variant HELD_OUT_FIRST_VARIANT + v instead of v (bench/transfer_testset.py), meshes no training spec
  can produce;
- textures: a training frame's texture variant is its surface's variant mod materials.variants (< 64); a test
  surface's texture variant is its held-out variant itself (>= MAX_VARIANTS), texture sets no training spec draws.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from seasynth.service.spec.dataset import DatasetSpec, apply_overrides, read_spec_file
from seasynth.service.spec.scene import MAX_VARIANTS

HELD_OUT_FIRST_VARIANT = MAX_VARIANTS  # test surfaces' variants start here; training variants stay below
RECIPES = Path(__file__).resolve().parent / "recipes"
REPO = Path(__file__).resolve().parents[1]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HeldOutGroup(_Model):
    """Frames of one kind of water and light: `frames` path-traced images of the base spec with `overrides`, at
    `spp` samples per pixel per half (None: the test set's)."""

    name: str = Field(pattern=r"^[a-z0-9-]+$")
    frames: int = Field(ge=1)
    spp: int | None = Field(None, ge=1)
    overrides: dict[str, Any] = {}


class HeldOutSet(_Model):
    """The held-out test set: group k's dataset seed is seed_first + k; spp per half (two halves, their PSNR to
    each other is the residual noise); the path tracer's max_depth and lamp housing (bench/pathtracer.py);
    exact_nee: shadow rays' transmittance through the water taken exactly (pathtracer_integrator: the same
    expectation as Mitsuba's volpath, less noise); min_contrast: a box whose object differs from its surroundings by less (8-bit sRGB codes,
    transfer_testset.contrast) is an ignored region."""

    seed_first: int = Field(ge=1, lt=2**62)
    spp: int = Field(ge=1)
    max_depth: int = Field(64, ge=2)
    lamp_housing_m: float = Field(0.05, ge=0.0)
    exact_nee: bool = False
    min_contrast: float = Field(6.0, ge=0.0)
    groups: list[HeldOutGroup] = Field(min_length=1)

    @property
    def frames(self) -> int:
        return sum(g.frames for g in self.groups)


class Training(_Model):
    """The detector's fixed recipe (bench/transfer_train.py). frames_1x: the paper's 1x dataset. Replicate r of
    a row trains on the row's data generated with dataset_seeds[r], initialised and shuffled with detector_seeds[r].
    lr: linear warm-up over warmup_steps, then cosine to zero at `steps`. Augmentation: a horizontal flip with
    probability hflip, brightness and contrast scaled by factors within 1 +- jitter. min_size, max_size: the
    detector resizes each image so its short side is min_size, its long side at most max_size (the model's own
    320 and 640 unless the recipe says)."""

    frames_1x: int = Field(ge=1)
    steps: int = Field(ge=1)
    batch: int = Field(ge=1)
    lr: float = Field(gt=0)
    warmup_steps: int = Field(ge=0)
    momentum: float = Field(0.9, ge=0, lt=1)
    weight_decay: float = Field(1e-4, ge=0)
    hflip: float = Field(0.5, ge=0, le=1)
    jitter: float = Field(0.2, ge=0, lt=1)
    dataset_seeds: list[int] = Field(min_length=1)
    detector_seeds: list[int] = Field(min_length=1)
    min_size: int = Field(320, ge=32)
    max_size: int = Field(640, ge=32)
    score_threshold: float = Field(0.001, ge=0, lt=1)  # detections kept for the metrics (COCO's habit: low)

    @model_validator(mode="after")
    def _replicates(self) -> Training:
        if len(self.dataset_seeds) != len(self.detector_seeds):
            raise ValueError("dataset_seeds and detector_seeds pair up: give as many of each")
        if len(set(self.dataset_seeds)) != len(self.dataset_seeds):
            raise ValueError("dataset_seeds repeat")
        return self


class Row(_Model):
    """One ablation row: the base spec with `overrides` at `size` x frames_1x frames."""

    name: str = Field(pattern=r"^[a-z0-9x-]+$")
    size: int = Field(1, ge=1)
    overrides: dict[str, Any] = {}


class Recipe(_Model):
    """The whole bench: base spec (repo-relative), resolution (training and test), test set, training, rows."""

    base_spec: str
    width: int = Field(ge=16)
    height: int = Field(ge=16)
    test: HeldOutSet
    training: Training
    rows: list[Row] = Field(min_length=1)

    @model_validator(mode="after")
    def _seeds_apart(self) -> Recipe:
        """Training seeds below the test range, so the two never share a frame generator."""
        if max(self.training.dataset_seeds) >= self.test.seed_first:
            raise ValueError(f"training.dataset_seeds must be below test.seed_first ({self.test.seed_first})")
        names = [r.name for r in self.rows]
        if len(set(names)) != len(names):
            raise ValueError(f"row names repeat: {names}")
        return self


def load_recipe(path: Path) -> Recipe:
    """The recipe in `path` (JSON), validated."""
    return Recipe.model_validate(json.loads(Path(path).read_text()))


def recipe_digest(recipe: Recipe) -> str:
    return hashlib.sha256(json.dumps(recipe.model_dump(), sort_keys=True).encode()).hexdigest()


def _spec(recipe: Recipe, overrides: dict[str, Any]) -> DatasetSpec:
    data = read_spec_file(REPO / recipe.base_spec)
    size = {"camera.width": recipe.width, "camera.height": recipe.height}
    return DatasetSpec.model_validate(apply_overrides(apply_overrides(data, size), overrides))


def row_spec(recipe: Recipe, row: Row, replicate: int) -> DatasetSpec:
    """The spec a user would generate for replicate `replicate` of `row` (with outputs.instance, so the COCO
    export reads its masks instead of rendering every frame again: the images are the same either way)."""
    t = recipe.training
    return _spec(recipe, {**row.overrides, "seed": t.dataset_seeds[replicate], "frames": row.size * t.frames_1x,
                          "outputs.instance": True})


def held_out_specs(recipe: Recipe) -> list[tuple[HeldOutGroup, DatasetSpec]]:
    """Each test group with its spec (seed seed_first + group index, its frames)."""
    return [(g, _spec(recipe, {**g.overrides, "seed": recipe.test.seed_first + k, "frames": g.frames}))
            for k, g in enumerate(recipe.test.groups)]


def training_variants(spec: DatasetSpec) -> tuple[set[int], set[int]]:
    """(procedural asset and terrain variants, texture variants) a training spec can draw."""
    counts = [ref.variants for group in (*spec.targets, spec.distractors) for ref in group.assets
              if ref.procedural is not None] + [spec.terrain.variants]
    shapes = set(range(max(counts)))
    return shapes, {v % spec.materials.variants for v in shapes}
