"""The GL renderer's shader programs: each variant (sources and defines) compiled and linked once per context, with
its uniforms' locations."""

from __future__ import annotations

from seasynth.service.errors import RenderError
from seasynth.worker.light.glsl import UNIFORMS as LIGHT_UNIFORMS
from seasynth.worker.render import shaders

# A linked program's GL name and the locations of its active uniforms, by name (shaders.UNIFORMS and the physical
# light's: a uniform the program lacks is absent, so a pass sets it only `if name in locs`).
Program = tuple[int, dict[str, int]]


class Programs:
    """The linked programs of one GL context, keyed by (vertex, fragment, defines). Every call needs the context
    current. gl: the PyOpenGL `GL` module; renderer_name names the GL renderer in errors."""

    def __init__(self, gl, renderer_name: str) -> None:
        self._gl = gl
        self._renderer_name = renderer_name
        self._linked: dict[tuple, Program] = {}

    def get(self, vertex: str | None, fragment: str, **defines: object) -> Program:
        """The program of a vertex and fragment shader, or of one compute shader (vertex None), each source with
        the defines (shaders.variant); built on first use. RenderError naming the GL renderer where it does not
        compile."""
        key = (vertex, fragment, tuple(sorted(defines.items())))
        got = self._linked.get(key)
        if got is not None:
            return got
        GL = self._gl
        # Imported here, not at the top: PyOpenGL picks its platform once, at its first import, which must come
        # after the renderer's prepare_environment (seasynth.worker.render.devices).
        from OpenGL.GL import shaders as gls

        if vertex is None:
            stages = [(fragment, GL.GL_COMPUTE_SHADER)]
        else:
            stages = [(vertex, GL.GL_VERTEX_SHADER), (fragment, GL.GL_FRAGMENT_SHADER)]
        try:
            prog = gls.compileProgram(
                *(gls.compileShader(shaders.variant(src, **defines), kind) for src, kind in stages), validate=False
            )
        except RuntimeError as err:
            raise RenderError(f"shader compilation failed on {self._renderer_name}: {err}") from err
        locs = {name: GL.glGetUniformLocation(prog, name) for name in (*shaders.UNIFORMS, *LIGHT_UNIFORMS)}
        got = (prog, {name: loc for name, loc in locs.items() if loc >= 0})
        self._linked[key] = got
        return got

    def clear(self) -> None:
        """Delete every program."""
        for prog, _ in self._linked.values():
            self._gl.glDeleteProgram(prog)
        self._linked.clear()
