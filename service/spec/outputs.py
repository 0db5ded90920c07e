"""The spec's outputs section: the files every frame gets, and the training formats and split written beside them."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, StrictBool, StrictFloat, StrictInt, field_validator

from seasynth.service.spec.types import SpecModel

EXPORT_FORMATS = ("coco", "yolo", "mcap")  # detector formats written beside the KITTI files (seasynth.worker.export)
IMAGE_SUFFIXES = {"png": ".png", "jpeg": ".jpg"}  # image_2's file suffix per outputs.image_format
SPLITS = ("train", "val", "test")
SPLIT_SUM_TOLERANCE = 1e-9


def split_problem(fractions: tuple[float, ...]) -> str | None:
    """Why `fractions` are no train, val, test split (three finite numbers >= 0 summing to 1 within 1e-9), or
    None. The one rule for outputs.split and `seasynth export --split`."""
    if len(fractions) != len(SPLITS):
        return f"give 3 fractions for train,val,test, got {len(fractions)}"
    if not all(math.isfinite(v) and v >= 0 for v in fractions):
        return "fractions must be finite and >= 0"
    if abs(math.fsum(fractions) - 1.0) > SPLIT_SUM_TOLERANCE:
        return f"fractions must sum to 1, they sum to {math.fsum(fractions):g}"
    return None


class Outputs(SpecModel):
    """The files every frame gets, and the training formats written beside them.

    coco, yolo, mcap: each shard of a service dataset also gets that format's files for its frames (one object per
    shard, listed in the manifest; `seasynth fetch --format` merges them); a local `seasynth generate` writes the
    whole dataset's export into OUT/export/{format}/. split: train, val, test fractions of those exports (frame i's
    split is drawn from (seed, i) alone: seasynth.worker.export.split_of).
    """

    labels: StrictBool = True
    meta: StrictBool = True
    depth: StrictBool = False
    instance: StrictBool = False
    # semantic/NNNNNN.png: uint8 class ids per pixel, 0 = terrain, water and distractors, i = the i-th class of
    # targets (1-based, the spec's order) on every pixel of its objects, whatever the label filters decide.
    semantic: StrictBool = False
    clean: StrictBool = False
    range: StrictBool = False
    coco: StrictBool = False
    yolo: StrictBool = False
    mcap: StrictBool = False
    split: tuple[StrictFloat, StrictFloat, StrictFloat] = (0.8, 0.1, 0.1)
    # image_2's encoding: png (lossless, the default) or jpeg at jpeg_quality (libjpeg-turbo through imagecodecs,
    # 4:2:0 chroma, baseline), for training on JPEG as most detector datasets are. depth, instance and clean stay
    # PNG: they are targets, not inputs. jpeg_quality other than its default needs jpeg (so that two specs of the same
    # files have one digest; a stored spec holds the default). The accuracy bench reports what JPEG costs in PSNR.
    image_format: Literal["png", "jpeg"] = "png"
    jpeg_quality: StrictInt = Field(95, ge=1, le=100)

    @field_validator("coco", "yolo", "mcap")
    @classmethod
    def _export_needs_labels(cls, on: bool, info) -> bool:
        if on and info.data.get("labels") is False:
            raise ValueError(f"needs outputs.labels: true (the {info.field_name} export's boxes are the label_2 "
                             "lines)")
        return on

    @field_validator("jpeg_quality")
    @classmethod
    def _quality_needs_jpeg(cls, q: int, info) -> int:
        if q != cls.model_fields["jpeg_quality"].default and info.data.get("image_format") != "jpeg":
            raise ValueError("is for image_format jpeg; with png (lossless) leave it out")
        return q

    @field_validator("split")
    @classmethod
    def _split(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        problem = split_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v

    @property
    def image_suffix(self) -> str:
        """image_2's file suffix: .png or .jpg."""
        return IMAGE_SUFFIXES[self.image_format]

    @property
    def exports(self) -> tuple[str, ...]:
        """The export formats switched on, in EXPORT_FORMATS order."""
        return tuple(f for f in EXPORT_FORMATS if getattr(self, f))
