"""The resolve as a compute shader (GPUs) writes the same bytes as the fragment resolve (software rasterisers), in
every output configuration, under both shader headers a context may need."""

import numpy as np
import pytest

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS, scene_light
from seasynth.worker.render import shaders

HEADERS = {
    "gl43": "#version 430 core",
    "gl41+extensions": "\n".join(["#version 410 core",
                                  *(f"#extension {e} : require" for e in shaders.COMPUTE_EXTENSIONS)]),
}
SPECS = {
    "physical-sun": ("examples/urchins.yaml", {}),
    "lamps": ("examples/night-dive.yaml", {}),
    "paper-haze": ("examples/urchins.yaml", {"water.model": "paper", "water.depth_m": None}),
    "outputs-high": ("examples/reef-physical.yaml", {"outputs.clean": True, "outputs.depth": True,
                                                      "outputs.range": True, "quality": "high"}),
    "noise-float": ("examples/urchins.yaml", {"noise.gaussian_sigma": 0.01}),
}


@pytest.fixture
def compute(renderer):
    """Switches the session renderer's resolve to the compute shader with a given header, and back."""
    before = renderer.compute_header, renderer.compute_resolve

    def use(header: str | None):
        renderer.compute_header, renderer.compute_resolve = header, header is not None

    yield use
    renderer.compute_header, renderer.compute_resolve = before


@pytest.mark.parametrize("header", list(HEADERS))
@pytest.mark.parametrize("name", list(SPECS))
def test_compute_resolve_writes_the_fragment_resolves_bytes(render_session, compute, header, name):
    path, overrides = SPECS[name]
    spec = load_spec(path, {"camera.width": 40, "camera.height": 30, **overrides})
    compute(None)
    expected = [render_session.frame_files(spec, i) for i in range(2)]
    compute(HEADERS[header])
    got = [render_session.frame_files(spec, i) for i in range(2)]
    for want, have in zip(expected, got):
        assert want.keys() == have.keys()
        assert [k for k in want if want[k] != have[k]] == []


def test_compute_resolve_reads_the_same_samples_for_audits(render_session, compute):
    spec = load_spec("examples/urchins.yaml", {"camera.width": 24, "camera.height": 18})
    scene = render_session.scene(spec, 1)
    view, items = render_session.view(spec, scene), render_session.draw_items(scene)
    compute(None)
    J0, R0 = render_session.renderer.samples(view, items, scene_light(scene), PRESETS["default"])
    compute(HEADERS["gl43"])
    J1, R1 = render_session.renderer.samples(view, items, scene_light(scene), PRESETS["default"])
    np.testing.assert_array_equal(J0, J1)
    np.testing.assert_array_equal(R0, R1)
    assert np.isfinite(R0).any() and J0.shape[0] == PRESETS["default"].per_pixel


def test_a_software_rasteriser_resolves_with_the_fragment_shader_and_a_gpu_with_the_compute_shader(renderer):
    software = "llvmpipe" in renderer.name.lower()
    assert renderer.compute_resolve is (not software)
    assert (renderer.compute_header is None) is software
