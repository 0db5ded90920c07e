"""Where a frame's GPU time goes: one process renders four frames of examples/urchins.yaml in a loop with two
frames in flight (frame k+1's passes are queued before frame k's reads are fetched, so the GPU never waits for
this process), and GL_TIMESTAMP queries between the stages give each stage's share of the GPU's timeline:

    python -m seasynth.bench.gpu_timeline WIDTHxHEIGHT [PRESET] [VARIANT ...]

Stages: shadow maps, clear (binding and clearing the surface target), surface (the multisampled surface pass),
resolve (water and the 8-bit codes, reads queued), ids (the ids pass and its read). A stage's time is the GPU's
time between the stamps before and after it (work still running from the stage before counts to it).

VARIANT (default: none): measurement-only changes of the surface target, whose frames are not valid:
`colour-rgba8`, `colour-rgba32f` (colour format instead of RGBA16F), `depth24` (24-bit depth instead of 32-bit
float), `clear-colour` (clear the colour as the renderer did before it kept it), `flat-shader` (a one-line surface
shader instead of the physical one). Results: bench/results/gpu/clear.md (0.5.1, whose surface pass also wrote a
range attachment; since 0.5.2 range comes from the depth: seasynth.worker.render.depth).
"""
from __future__ import annotations

import collections
import ctypes
import statistics
import sys
import time

VARIANTS = ("colour-rgba8", "colour-rgba32f", "depth24", "clear-colour", "flat-shader")
FLAT_SURFACE = """
#version 330 core
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_col;
uniform vec3 u_scale;
uniform vec3 u_bias;
layout(location = 0) out vec4 o_J;
void main() {
    o_J = vec4((v_col * u_scale + u_bias) * max(dot(normalize(v_nrm), vec3(0.0, 0.0, -1.0)), 0.0), 1.0);
}
"""


def apply_variants(variants: list[str]) -> None:
    from OpenGL import GL

    import seasynth.worker.light.glsl as glsl
    from seasynth.worker.render import gl as gl_renderer
    from seasynth.worker.render import targets

    if "flat-shader" in variants:
        glsl.SURFACE = FLAT_SURFACE
    colour = {"colour-rgba8": GL.GL_RGBA8, "colour-rgba32f": GL.GL_RGBA32F}
    fmt = next((colour[v] for v in variants if v in colour), GL.GL_RGBA16F)
    depth = GL.GL_DEPTH_COMPONENT24 if "depth24" in variants else GL.GL_DEPTH_COMPONENT32F

    def surface(self, w, h, msaa, with_range):
        def build():
            t = self.new_fbo()
            self._attach_texture(t, 0, fmt, w, h, msaa)
            if with_range:
                self._attach_texture(t, 1, depth, w, h, msaa, attachment=GL.GL_DEPTH_ATTACHMENT)
            else:
                self._attach_renderbuffer(t, GL.GL_DEPTH_ATTACHMENT, depth, w, h, msaa)
            return t
        return self.get(("surface", w, h, msaa, with_range), build)

    targets.Targets.surface = surface
    if "clear-colour" in variants:
        real = gl_renderer.GLRenderer.bind_and_clear
        gl_renderer.GLRenderer.bind_and_clear = lambda self, t, clears: real(
            self, t, ("colour",) if clears == ("keep",) else clears)


class Stamps:
    """GL_TIMESTAMP queries of one frame, in order."""

    def __init__(self, GL) -> None:
        from OpenGL.raw.GL.VERSION.GL_3_3 import glGetQueryObjectui64v

        self.GL, self._get, self.marks = GL, glGetQueryObjectui64v, []

    def __call__(self, name: str) -> None:
        q = self.GL.glGenQueries(1)[0]
        self.GL.glQueryCounter(q, self.GL.GL_TIMESTAMP)
        self.marks.append((name, q))

    def stages(self) -> list[tuple[str, float]]:
        """(stage, GPU ms) between consecutive stamps; deletes the queries."""
        out, t = [], []
        for name, q in self.marks:
            v = ctypes.c_uint64(0)
            self._get(q, self.GL.GL_QUERY_RESULT, ctypes.cast(ctypes.byref(v), ctypes.POINTER(ctypes.c_uint64)))
            t.append((name, v.value))
        self.GL.glDeleteQueries(len(self.marks), [q for _, q in self.marks])
        return [(n1, (t1 - t0) / 1e6) for (_, t0), (n1, t1) in zip(t, t[1:])]


def main(w: int, h: int, preset_name: str, variants: list[str], seconds: float = 4.0) -> None:
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import PRESETS, RenderSession, scene_light
    from seasynth.worker.render import Passes, gl_light

    apply_variants(variants)
    spec = load_spec("examples/urchins.yaml", {"camera.width": w, "camera.height": h})
    with RenderSession() as s:
        r = s.renderer
        GL = r.gl
        real_maps, real_clear = gl_light.shadow_maps, r.bind_and_clear
        current: list[Stamps] = []

        def maps(*a, **k):
            out = real_maps(*a, **k)
            current[-1]("shadow maps")
            return out

        def bind_and_clear(t, clears):
            real_clear(t, clears)
            if clears[0] in ("keep", "colour"):
                current[-1]("clear")

        gl_light.shadow_maps, r.bind_and_clear = maps, bind_and_clear
        stage_name = {"render": "surface", "formation": "resolve", "ids": "ids"}

        def submit(view, items, light, water):
            r._platform.make_current()
            st = Stamps(GL)
            current.append(st)
            st("begin")
            queued = r.queue(view, items, light, water, PRESETS[preset_name], Passes(ids=True, srgb8=True),
                             stage=lambda x: st(stage_name[x]))
            return queued, st

        def fetch(handle):
            queued, st = handle
            r.fetch(queued)
            return st.stages()

        frames = []
        for i in range(4):
            scene = s.scene(spec, i)
            frames.append((s.view(spec, scene), s.draw_items(scene), scene_light(scene), scene.water))
        for f in frames:
            fetch(submit(*f))
        per = collections.defaultdict(list)
        inflight = collections.deque()
        t0, n = time.perf_counter(), 0
        while time.perf_counter() - t0 < seconds:
            inflight.append(submit(*frames[n % 4]))
            if len(inflight) == 2:
                for name, ms in fetch(inflight.popleft()):
                    per[name].append(ms)
            n += 1
        while inflight:
            fetch(inflight.popleft())
        elapsed = time.perf_counter() - t0
    label = "+".join(variants) or "as built"
    print(f"{w}x{h} {preset_name} ({label}): {n / elapsed:.1f} frames/s, one process, two frames in flight")
    print("| stage | GPU ms a frame (mean) |\n|---|---|")
    for name, v in per.items():
        print(f"| {name} | {statistics.mean(v):.3f} |")
    print(f"| sum | {sum(statistics.mean(v) for v in per.values()):.3f} |", flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    size = tuple(int(x) for x in sys.argv[1].split("x"))
    preset = sys.argv[2] if len(sys.argv) > 2 else "default"
    chosen = sys.argv[3:]
    unknown = [v for v in chosen if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant(s) {unknown}; known: {', '.join(VARIANTS)}")
    main(*size, preset, chosen)
