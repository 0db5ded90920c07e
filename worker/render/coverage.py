"""Pixels each object covers when drawn alone (KITTI occlusion needs them), counted on the GPU for many objects with
one wait. Used by GLRenderer (seasynth.worker.render.gl)."""

from __future__ import annotations

from seasynth.worker.render import DrawItem, View
from seasynth.worker.render.shaders import DEPTH_ONLY, VERTEX

Region = tuple[int, int, int, int]  # (left, top, right, bottom) inclusive pixel bounds


def clipped(region: Region | None, width: int, height: int) -> Region | None:
    """region cut to the image (the whole image for None); None where nothing of it is left."""
    x0, y0, x1, y1 = (0, 0, width - 1, height - 1) if region is None else region
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
    return None if x1 < x0 or y1 < y0 else (x0, y0, x1, y1)


def pixels_alone(r, view: View, jobs: list[tuple[DrawItem, Region | None]]) -> list[int]:
    """For each (item, region): pixels (at pixel centres) the item covers when drawn with nothing else in the scene,
    on GLRenderer `r` (its context current). region bounds the item's projection: only it is cleared and drawn.

    Each item is drawn into a stencil buffer cleared over its region, passing where the stencil is still 0 and
    raising it: a covered pixel passes once, however many of the item's triangles cover its centre, so the item's
    occlusion query counts its pixels (the pixels a lone id pass would mark). Every item is drawn before any count is
    read, so the GPU is waited for once, not once an item.
    """
    GL = r.gl
    w, h = view.width, view.height
    regions = [clipped(region, w, h) for _, region in jobs]
    drawn = [k for k, region in enumerate(regions) if region is not None]
    counts = [0] * len(jobs)
    if not drawn:
        return counts
    t = r.targets.stencil(w, h)
    GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, t.fbo)
    prog, locs = r.programs.get(VERTEX, DEPTH_ONLY)
    GL.glUseProgram(prog)
    r.set_view(locs, view, w, h)
    GL.glDisable(GL.GL_DEPTH_TEST)
    GL.glEnable(GL.GL_SCISSOR_TEST)
    GL.glEnable(GL.GL_STENCIL_TEST)
    GL.glStencilFunc(GL.GL_EQUAL, 0, 0xFF)
    GL.glStencilOp(GL.GL_KEEP, GL.GL_KEEP, GL.GL_INCR)
    queries = list(GL.glGenQueries(len(drawn)))
    try:
        for k, query in zip(drawn, queries):
            x0, y0, x1, y1 = regions[k]
            GL.glScissor(x0, y0, x1 - x0 + 1, y1 - y0 + 1)
            GL.glClearBufferiv(GL.GL_STENCIL, 0, [0])
            GL.glBeginQuery(GL.GL_SAMPLES_PASSED, query)
            r.draw(view, [jobs[k][0]], locs, lit=False, ids=False)
            GL.glEndQuery(GL.GL_SAMPLES_PASSED)
        for k, query in zip(drawn, queries):
            counts[k] = int(GL.glGetQueryObjectuiv(query, GL.GL_QUERY_RESULT))
    finally:
        GL.glDeleteQueries(len(queries), queries)
        GL.glDisable(GL.GL_STENCIL_TEST)
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glEnable(GL.GL_DEPTH_TEST)
    return counts
