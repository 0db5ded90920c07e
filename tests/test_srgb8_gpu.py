"""8-bit sRGB on the GPU (Passes.srgb8, srgb.GLSL_SRGB8): the shader's codes equal encode_srgb8 on every
threshold, on the float32 just below it, on the hard values, and on whole frames; NaN is refused as on the CPU."""

import numpy as np
import pytest

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS, scene_light
from seasynth.worker.frame.srgb import GLSL_SRGB8, SRGB8_THRESHOLDS_F32, encode_srgb8
from seasynth.worker.render import Passes
from seasynth.worker.render.shaders import FULLSCREEN

PROBE = """
#version 330 core
uniform sampler2D u_vals;
layout(location = 0) out vec4 o;
""" + GLSL_SRGB8 + """
void main() {
    vec4 v = texelFetch(u_vals, ivec2(gl_FragCoord.xy), 0);
    o = srgb8(v.rgb);
}
"""


def gpu_codes(renderer, values: np.ndarray) -> np.ndarray:
    """(n, 4) uint8: the shader's codes of float32 values (one value per pixel in all three channels; alpha: NaN)."""
    GL = renderer.gl
    renderer._platform.make_current()
    n = values.size
    rgb = np.repeat(values.astype(np.float32)[:, None], 4, axis=1).reshape(1, n, 4)
    tex = GL.glGenTextures(1)
    try:
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA32F, n, 1, 0, GL.GL_RGBA, GL.GL_FLOAT, rgb)
        for k in (GL.GL_TEXTURE_MIN_FILTER, GL.GL_TEXTURE_MAG_FILTER):
            GL.glTexParameteri(GL.GL_TEXTURE_2D, k, GL.GL_NEAREST)
        target = renderer.targets.resolve(n, 1, (GL.GL_RGBA8,))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, target.fbo)
        GL.glDrawBuffers([GL.GL_COLOR_ATTACHMENT0])
        GL.glDisable(GL.GL_DEPTH_TEST)
        prog, locs = renderer.programs.get(FULLSCREEN, PROBE)
        GL.glUseProgram(prog)
        GL.glUniform1i(GL.glGetUniformLocation(prog, "u_vals"), 0)
        GL.glUniform1fv(locs["u_srgb_thr"], 255, SRGB8_THRESHOLDS_F32)
        GL.glViewport(0, 0, n, 1)
        GL.glBindVertexArray(renderer.empty_vao)
        GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
        GL.glBindVertexArray(0)
        GL.glEnable(GL.GL_DEPTH_TEST)
        rb = renderer.readback
        return rb.fetch(rb.queue(0, n, 1, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, np.uint8, 4))[0]
    finally:
        GL.glDeleteTextures([tex])


def test_every_threshold_and_the_float_below_it_and_the_hard_values(renderer):
    t = SRGB8_THRESHOLDS_F32
    below = np.nextafter(t, np.float32(-np.inf))
    hard = np.array([0.0, -0.0, -1e-30, -1.0, 1e-45, 1.0, 1.0000001, 2.0, 1e30, np.inf, -np.inf], np.float32)
    values = np.concatenate([t, below, hard, np.random.default_rng(0).uniform(-0.1, 1.1, 512).astype(np.float32)])
    got = gpu_codes(renderer, values)
    np.testing.assert_array_equal(got[:, 0], encode_srgb8(values))
    assert np.all(got[:, 0] == got[:, 1]) and np.all(got[:, 3] == 0)
    # each threshold starts its code, the float below it is one code less
    np.testing.assert_array_equal(got[:255, 0], np.arange(1, 256))
    np.testing.assert_array_equal(got[255:510, 0], np.arange(0, 255))


def test_nan_is_flagged(renderer):
    got = gpu_codes(renderer, np.array([0.5, np.nan, 0.25], np.float32))
    assert got[:, 3].tolist() == [0, 1, 0]


@pytest.mark.parametrize("example", ["urchins", "reef-physical", "night-dive"])
def test_frames_read_back_as_codes_equal_the_cpu_encoding_of_the_float_image(render_session, example):
    s = render_session
    spec = load_spec(f"examples/{example}.yaml", {"camera.width": 64, "camera.height": 48})
    for i in range(2):
        scene = s.scene(spec, i)
        view, items = s.view(spec, scene), s.draw_items(scene)
        args = (view, items, scene_light(scene), scene.water, PRESETS[spec.quality])
        floats = s.renderer.render(*args, Passes(range=True))
        codes = s.renderer.render(*args, Passes(range=True, srgb8=True))
        assert codes.image.dtype == np.uint8 and "read image srgb8" in codes.passes
        np.testing.assert_array_equal(codes.image, encode_srgb8(floats.image))
        np.testing.assert_array_equal(codes.range_m, floats.range_m)
