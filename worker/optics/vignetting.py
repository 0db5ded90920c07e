"""Vignetting: the irradiance a lens delivers off its axis falls as cos^4 of the field angle (spec
`camera.vignetting`, the exponent's strength s: gain cos(theta)^(4 s)).

One number tied to the physical law rather than polynomial coefficients in a normalised radius: the field angle
comes from K, so a strength means the same falloff at every resolution and field of view, and 1 is exactly a thin
lens's natural vignetting; strengths above 1 stand in for the extra mechanical vignetting of a housing's port."""

from __future__ import annotations

import dataclasses

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.optics.base import Plain, Shot, field_cosine
from seasynth.worker.render import RenderResult


def vignetting_gain(K: np.ndarray, width: int, height: int, strength: float) -> np.ndarray:
    """(h, w) float32: cos(theta)^(4 strength), theta the angle between a pixel centre's ray and the optical axis
    (exactly 1 on the axis)."""
    cos_field = field_cosine(K, width, height)
    return (cos_field ** (4.0 * strength)).astype(np.float32)


class Vignetting(Plain):
    name = "vignetting"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.camera.vignetting > 0

    def prepare(self, shot: Shot) -> None:
        shot.float_image = True

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        view = shot.view
        gain = vignetting_gain(view.K, view.width, view.height, shot.spec.camera.vignetting)[..., None]
        shot.record[self.name] = {"strength": shot.spec.camera.vignetting, "law": "cos(field angle)^(4 strength)",
                                  "min_gain": float(gain.min())}
        clean = None if result.clean is None else result.clean * gain
        return dataclasses.replace(result, image=result.image * gain, clean=clean)
