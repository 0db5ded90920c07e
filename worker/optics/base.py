"""The interface every optical effect implements (see seasynth.worker.optics)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.light.volume import pixel_rays
from seasynth.worker.render import DrawItem, RenderResult, View
from seasynth.worker.scene.sample import Scene

# Renders `items` from `view` with the frame's light, water, sampling and passes.
RenderFn = Callable[[View, list[DrawItem]], RenderResult]


@dataclass
class Shot:
    """One frame on its way through the effects.

    view: the output camera (labels, calib and meta describe it); render_view: what is rasterised (a pinhole,
    wider than `view` where a port or lens resamples it); items: what the camera draws (the scene's items plus
    any particles: sonar and labels' per-object renders use the scene's own list); float_image: an effect needs
    the float image (the GPU's 8-bit encode is skipped); needs: render passes an effect reads whether or not the
    outputs ask for them ("clean", "ids", "range": seasynth.worker.render.Passes); record: meta's "optics" entry,
    by effect name (the sensor's noise keeps meta's own "noise" entry); range_norms: (h, w) float32 range / z-depth
    of each output pixel where an effect's rays do not all leave the pinhole (None: the pinhole's ray norms).
    """

    spec: DatasetSpec
    index: int
    scene: Scene
    view: View
    render_view: View
    items: list[DrawItem]
    float_image: bool = False
    needs: set[str] = field(default_factory=set)
    record: dict = field(default_factory=dict)
    range_norms: np.ndarray | None = None


class Effect(Protocol):
    name: str
    shapes_view: bool  # its prepare sets shot.render_view (a port or lens): it prepares before every other effect

    def on(self, spec: DatasetSpec) -> bool: ...

    def prepare(self, shot: Shot) -> None: ...

    def expose(self, shot: Shot, render: RenderFn) -> RenderResult | None:
        """The frame's render, or None to leave it to the next effect (at most one effect exposes a frame)."""

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult: ...


class Plain:
    """An effect's defaults: prepares nothing, leaves the exposure alone, develops nothing."""

    name = "plain"
    shapes_view = False

    def on(self, spec: DatasetSpec) -> bool:
        return False

    def prepare(self, shot: Shot) -> None:
        return None

    def expose(self, shot: Shot, render: RenderFn) -> RenderResult | None:
        return None

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        return result


def field_cosine(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h, w) float64, read-only: the cosine of the angle between each pixel centre's ray and the optical axis (the
    z of its unit direction). Cached per intrinsics and size (a few cameras' worth: 16 MB each at 1920x1080)."""
    return _field_cosine(np.asarray(K, np.float64).tobytes(), width, height)


@functools.lru_cache(maxsize=4)
def _field_cosine(K_bytes: bytes, width: int, height: int) -> np.ndarray:
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    out = np.ascontiguousarray(pixel_rays(K, width, height, np.eye(4))[1][..., 2])
    out.flags.writeable = False
    return out
