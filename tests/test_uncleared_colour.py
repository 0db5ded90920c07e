"""The surface pass does not clear its colour where it draws for range (the resolve reads where anything was drawn,
and each sample's range, from the depth, and takes colour 0 and range +inf elsewhere): whatever a previous frame left
at a sample with no surface must never reach an output. Here the kept attachment is overwritten with NaN and
infinities before every surface pass, and every file of the frame must still be the same bytes."""

import numpy as np
import pytest

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS
from seasynth.worker.render import Passes
from tests.test_resolve_compute import SPECS

CASES = {
    **SPECS,
    # The paper's haze with beta_D = 0: an uncovered sample's colour would pass through unattenuated.
    "paper-beta-zero": ("examples/urchins.yaml", {
        "water.model": "paper", "water.jerlov": [], "water.depth_m": None,
        "water.beta_D": {"min": [0, 0, 0], "max": [0, 0, 0]},
        "water.B_inf": {"min": [0.1, 0.2, 0.3], "max": [0.1, 0.2, 0.3]}, "outputs.clean": True}),
    "fast-clean-range": ("examples/urchins.yaml", {"quality": "fast", "outputs.clean": True, "outputs.range": True}),
    "water-off": ("examples/urchins.yaml", {"water.enabled": False, "water.depth_m": None}),
}
JUNK = np.array([np.nan, np.inf, -np.inf, np.nan], np.float32)


def junk_in_kept_colour(renderer, monkeypatch) -> list[int]:
    """Fills every attachment the renderer binds without clearing with NaN and infinities; counts them."""
    from OpenGL import GL

    kept = []
    real = renderer.bind_and_clear

    def bind_and_clear(t, clears):
        real(t, clears)
        for slot, what in enumerate(clears):
            if what == "keep":
                GL.glClearBufferfv(GL.GL_COLOR, slot, JUNK)
                kept.append(slot)

    monkeypatch.setattr(renderer, "bind_and_clear", bind_and_clear)
    return kept


def open_water_pixels(session, spec, index: int) -> int:
    scene = session.scene(spec, index)
    r = session.renderer.render(session.view(spec, scene), session.draw_items(scene), scene.lighting, None,
                                PRESETS["draft"], Passes(range=True))
    return int(np.isinf(r.range_m).sum())


@pytest.mark.parametrize("name", list(CASES))
def test_colour_left_by_earlier_frames_never_reaches_a_frames_files(render_session, renderer, monkeypatch, name):
    path, overrides = CASES[name]
    # A near far plane: beyond it no surface is drawn, so every frame has samples with range +inf.
    spec = load_spec(path, {"camera.width": 40, "camera.height": 30, "camera.clip": [0.02, 1.2], **overrides})
    assert all(open_water_pixels(render_session, spec, i) > 0 for i in range(2))
    expected = [render_session.frame_files(spec, i) for i in range(2)]
    kept = junk_in_kept_colour(renderer, monkeypatch)
    got = [render_session.frame_files(spec, i) for i in range(2)]
    for want, have in zip(expected, got):
        assert want.keys() == have.keys()
        assert [k for k in want if want[k] != have[k]] == []
    # Every frame here has water (so range) and keeps its colour (slot 0; its only colour attachment), except
    # without water: no range is needed, and the colour is cleared.
    assert kept == ([] if name == "water-off" else [0, 0])
