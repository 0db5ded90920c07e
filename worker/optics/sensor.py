"""The sensor: what turns the light on each pixel into recorded values. Today additive Gaussian noise in linear
light (spec `noise.gaussian_sigma`), drawn from the frame's noise stream."""

from __future__ import annotations

import dataclasses

import numpy as np

from seasynth.service.seeds import STREAM_NOISE, frame_rng
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.optics.base import Plain, Shot
from seasynth.worker.render import RenderResult


class Sensor(Plain):
    name = "noise"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.noise.gaussian_sigma > 0

    def prepare(self, shot: Shot) -> None:
        shot.float_image = True

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        sigma = shot.spec.noise.gaussian_sigma
        rng = frame_rng(shot.spec.seed, shot.index, STREAM_NOISE)
        image = result.image + rng.normal(0.0, sigma, result.image.shape).astype(np.float32)
        shot.record[self.name] = {"gaussian_sigma_linear": sigma}
        return dataclasses.replace(result, image=image)
