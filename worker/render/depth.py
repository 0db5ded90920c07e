"""The camera passes' depth convention: reversed (1 at the near plane, 0 at the far one) in a 32-bit float buffer,
through glClipControl's [0, 1] depth range, so a sample's depth keeps its distance to float32's relative precision
at every range (conventional depth loses it with distance: at 50 m from a 5 cm near plane it keeps 1 part in
~10^4). The surface pass's resolve therefore derives each sample's range from its depth, and the pass writes no
range attachment: on an H100 the multisampled pass costs the bytes a sample holds (bench/results/gpu/clear.md).

Shadow maps keep GL's conventional depth (`conventional`), their samplers compare with LEQUAL.
"""

from __future__ import annotations

import contextlib
import ctypes

import numpy as np

from seasynth.service.errors import RenderError
from seasynth.worker.render import View
from seasynth.worker.render.shaders import context_has, context_version

LOWER_LEFT, NEGATIVE_ONE_TO_ONE, ZERO_TO_ONE = 0x8CA1, 0x935E, 0x935F  # glClipControl's enums (GL 4.5)
SAMPLE_POSITION = 0x8E50
FAR_DEPTH = 0.0  # what the camera passes clear depth to: nothing drawn


def projection(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """(4, 4) float64 clip-from-camera for KITTI camera coordinates, reversed depth in [0, 1]: a point at z metres
    (camera frame, forward) gets depth near (far - z) / (z (far - near)), 1 at the near plane and 0 at the far one.

    Row v of the image lands on framebuffer row v (GL's bottom row first), so read-back arrays are already in
    image order; pixel (u, v) centres sit at integer coordinates, matching K.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array(
        [
            [2 * fx / width, K[0, 1] * 2 / width, 2 * (cx + 0.5) / width - 1, 0],
            [0, 2 * fy / height, 2 * (cy + 0.5) / height - 1, 0],
            [0, 0, -near / (far - near), far * near / (far - near)],
            [0, 0, 1, 0],
        ],
        dtype=np.float64,
    )


def z_from_depth(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """The camera-frame z (metres) of reversed depth values: near far / (depth (far - near) + near); the resolve's
    formula (RANGE_FUNCTION), in float64 for tests."""
    return near * far / (np.asarray(depth, np.float64) * (far - near) + near)


class ClipControl:
    """glClipControl of the current context (PyOpenGL 3.1.0 has no GL 4.5 entry points: it is called through
    ctypes). Raises RenderError where the context has neither GL 4.5 nor ARB_clip_control."""

    def __init__(self, GL, renderer_name: str) -> None:
        # Imported here: PyOpenGL picks its platform at its first import (after devices.prepare_environment).
        from OpenGL import platform

        address = platform.PLATFORM.getExtensionProcedure(b"glClipControl")
        if not (context_version(GL) >= (4, 5) or context_has(GL, ("GL_ARB_clip_control",))) or not address:
            raise RenderError(f"{renderer_name} lacks glClipControl (GL 4.5 or ARB_clip_control), which the "
                              "renderer's reversed float depth needs")
        self._gl = GL
        self._call = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_uint)(address)

    def camera(self) -> None:
        """The camera passes' state: [0, 1] clip depth, nearer is greater, cleared to FAR_DEPTH."""
        GL = self._gl
        self._call(LOWER_LEFT, ZERO_TO_ONE)
        GL.glDepthFunc(GL.GL_GREATER)
        GL.glClearDepth(FAR_DEPTH)

    @contextlib.contextmanager
    def conventional(self):
        """GL's default depth inside the block ([-1, 1] clip depth, nearer is less, cleared to 1); the camera
        passes' state after it."""
        GL = self._gl
        self._call(LOWER_LEFT, NEGATIVE_ONE_TO_ONE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glClearDepth(1.0)
        try:
            yield
        finally:
            self.camera()


def sample_positions(GL, msaa: int) -> np.ndarray:
    """(msaa, 2) float32: each sample's position within its pixel ([0, 1), x right, y up) in the multisampled
    framebuffer bound now; the pixel centre for one sample."""
    if msaa <= 1:
        return np.full((1, 2), 0.5, np.float32)
    out = np.zeros((msaa, 2), np.float32)
    for i in range(msaa):
        GL.glGetMultisamplefv(SAMPLE_POSITION, i, out[i])  # PyOpenGL 3.1.0 wants the output array given
    return out


def range_uniforms(GL, locs: dict[str, int], view: View, positions: np.ndarray) -> None:
    """The resolve's uniforms that turn a sample's depth into its range (RANGE_FUNCTION)."""
    n, f = float(view.near), float(view.far)
    GL.glUniform3f(locs["u_depth"], n * f, f - n, n)
    GL.glUniformMatrix3fv(locs["u_K_inv"], 1, GL.GL_TRUE, np.linalg.inv(view.K).astype(np.float32))
    GL.glUniform2fv(locs["u_sample_pos"], len(positions), np.ascontiguousarray(positions, np.float32))


# A sample's range from its reversed depth d (> 0 where anything was drawn): z from d, times the length of the
# sample's ray through K^-1 (image coordinates: pixel centres at integers, SUPERSAMPLE framebuffer pixels an image
# pixel a side).
RANGE_FUNCTION = """
uniform vec3 u_depth;                  // near * far, far - near, near (metres)
uniform vec2 u_sample_pos[SAMPLES];    // each sample's position within its framebuffer pixel
float sample_range(ivec2 q, int s, float d) {
    vec2 uv = (vec2(q) + u_sample_pos[s]) / float(SUPERSAMPLE) - 0.5;
    return u_depth.x / (d * u_depth.y + u_depth.z) * length(u_K_inv * vec3(uv, 1.0));
}
"""
