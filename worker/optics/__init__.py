"""What stands between the scene and the recorded image: the water column's particles and blur, the housing's
port, the lens and the sensor.

Each effect is a module of this package behind one small interface (`Effect`), listed in EFFECTS in the order
light meets it. An effect is off unless its spec says otherwise, and an effect that is off costs nothing and
changes no byte. It may act at three points of a frame:

- `prepare`: before the render, on what is drawn and from where (marine snow adds particles to the camera's
  draw list; a port or a distorting lens renders a wider pinhole view that `develop` resamples);
- `expose`: the render itself (motion blur renders several instants of the exposure and averages them);
- `develop`: after the render, on its float buffers (forward-scatter blur, the port's and lens's resampling,
  depth of field, vignetting, then the sensor).

Every effect that ran adds its record to meta (`Optics.record`); draws come from the frame's own seed streams
(seasynth.service.seeds), so switching an effect on changes no other draw.
"""

from __future__ import annotations

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.optics import dof, forward_scatter, geometry, motion, particles, sensor, vignetting
from seasynth.worker.optics.base import Effect, RenderFn, Shot
from seasynth.worker.render import DrawItem, RenderResult, View
from seasynth.worker.scene.sample import Scene


def effects() -> list[Effect]:
    """Every effect, in the order light meets it."""
    return [particles.MarineSnow(), forward_scatter.ForwardScatter(), geometry.Geometry(), dof.DepthOfField(),
            motion.MotionBlur(), vignetting.Vignetting(), sensor.Sensor()]


class Optics:
    """The effects a spec turns on, applied to one frame: prepare, expose, develop."""

    def __init__(self, spec: DatasetSpec, index: int, scene: Scene, view: View, items: list[DrawItem]) -> None:
        self.active = [e for e in effects() if e.on(spec)]
        self.shot = Shot(spec=spec, index=index, scene=scene, view=view, render_view=view, items=list(items))
        # Effects that choose the rendered view prepare first, so what the others add (particles) fills that view.
        for effect in sorted(self.active, key=lambda e: not e.shapes_view):
            effect.prepare(self.shot)

    @property
    def float_image(self) -> bool:
        return self.shot.float_image

    def render(self, render: RenderFn) -> RenderResult:
        shot = self.shot
        result = None
        for effect in self.active:
            result = effect.expose(shot, render)
            if result is not None:
                break
        if result is None:
            result = render(shot.render_view, shot.items)
        for effect in self.active:
            result = effect.develop(shot, result)
        return result

    @property
    def record(self) -> dict:
        return self.shot.record

    def pixels_alone(self, renderer, jobs: list[tuple[DrawItem, tuple[int, int, int, int] | None]]) -> list[int]:
        """Each item's pixels in the output image when drawn alone, counted as the frame's instance image is made
        (regions bound the item's pinhole projection; an effect that resamples counts the whole render)."""
        for effect in self.active:
            if hasattr(effect, "pixels_alone"):
                return effect.pixels_alone(self.shot, renderer, [item for item, _ in jobs])
        return renderer.pixels_alone_many(self.shot.view, jobs)


