"""An uploaded mesh's thumbnail without OpenGL (the API image has none): flat-shaded triangles z-buffered in NumPy,
seen in an orthographic three-quarter view, the picture the playground's asset picker shows beside the kinds'.

Drawn in the upload's check process (seasynth.api.mesh_check), which has loaded the mesh already, within its memory
budget. Untextured: every face takes one colour, shaded by its angle to a fixed light.
"""

from __future__ import annotations

import io

import numpy as np

WIDTH, HEIGHT = 128, 96  # as the procedural kinds' thumbnails (api/static/playground/kinds/)
SUPERSAMPLE = 3  # drawn at 3x, then averaged: edges smooth, triangles smaller than a pixel still count
AZIMUTH_DEG, ELEVATION_DEG = -35.0, 30.0  # the viewer: front right of the mesh (+x right, +z up), above it
MARGIN = 0.08  # of the picture on each side
COLOUR = np.array([214, 168, 120], dtype=np.float64)  # a sandy clay: readable on the picker's light tiles
LIGHT = np.array([-0.4, 0.6, 0.7])  # in view coordinates (right, up, toward the viewer): from the upper left
AMBIENT = 0.35
CHUNK_SAMPLES = 1 << 21  # (triangle, pixel) candidates tested at once: bounds the memory of a dense mesh


def view_axes(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3, 3) float64 rows: the view's right, up and toward-the-viewer axes in world coordinates (+z up)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    toward = np.array([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)])
    right = np.cross([0.0, 0.0, 1.0], toward)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(toward, right), toward])


def project(vertices: np.ndarray, axes: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n, 3) float64: vertices (n, 3, world units) as (column, row, depth) in a width x height picture, the mesh's
    projection scaled to fit within the margins and centred; depth grows toward the viewer, in the same scale."""
    v = np.asarray(vertices, dtype=np.float64) @ axes.T
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    span = np.maximum(hi - lo, 1e-12)
    scale = min(width * (1 - 2 * MARGIN) / span[0], height * (1 - 2 * MARGIN) / span[1])
    centre = (lo + hi) / 2
    col = width / 2 + (v[:, 0] - centre[0]) * scale
    row = height / 2 - (v[:, 1] - centre[1]) * scale  # rows grow downwards
    return np.column_stack([col, row, v[:, 2] * scale])


def face_shades(vertices: np.ndarray, faces: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(m,) float64 in [AMBIENT, 1]: each face's brightness, Lambert on both sides (windings are not trusted)."""
    tri = np.asarray(vertices, dtype=np.float64)[faces] @ axes.T
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    cos = np.abs(normal @ (LIGHT / np.linalg.norm(LIGHT))) / np.where(length > 0, length, 1.0)
    return AMBIENT + (1 - AMBIENT) * cos


def rasterise(tri: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer triangles `tri` (m, 3, 3) float64 (column, row, depth per corner; depth toward the viewer) onto a
    width x height grid of pixel centres. Returns (face, depth): (height, width) int64, the index of the nearest
    triangle covering each pixel's centre (-1: none), and (height, width) float64 its depth there (-inf: none).
    A centre on an edge counts as inside; of two triangles at one depth the lower index wins."""
    face = np.full(height * width, -1, dtype=np.int64)
    zbuf = np.full(height * width, -np.inf)
    x, y = tri[:, :, 0], tri[:, :, 1]
    # Pixel (i, j) has its centre at (i + 0.5, j + 0.5): the centres within each triangle's bounding box.
    i0 = np.clip(np.ceil(x.min(axis=1) - 0.5), 0, width).astype(np.int64)
    i1 = np.clip(np.floor(x.max(axis=1) - 0.5), -1, width - 1).astype(np.int64)
    j0 = np.clip(np.ceil(y.min(axis=1) - 0.5), 0, height).astype(np.int64)
    j1 = np.clip(np.floor(y.max(axis=1) - 0.5), -1, height - 1).astype(np.int64)
    nx, ny = np.maximum(i1 - i0 + 1, 0), np.maximum(j1 - j0 + 1, 0)
    area = nx * ny
    den = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0])
    area[np.abs(den) < 1e-12] = 0  # edge-on or degenerate: covers no area
    ends = np.cumsum(area)
    start = 0
    while start < len(tri):
        # A chunk of whole triangles with about CHUNK_SAMPLES candidates (one triangle has at most width * height).
        stop = max(int(np.searchsorted(ends, ends[start] - area[start] + CHUNK_SAMPLES, side="right")), start + 1)
        _draw_chunk(tri, np.arange(start, stop), i0, j0, nx, area, den, width, face, zbuf)
        start = stop
    return face.reshape(height, width), zbuf.reshape(height, width)


def _draw_chunk(tri, ids, i0, j0, nx, area, den, width, face, zbuf) -> None:
    n = area[ids]
    t = np.repeat(ids, n)  # one entry per (triangle, candidate pixel)
    k = np.arange(len(t)) - np.repeat(np.cumsum(n) - n, n)
    px, py = i0[t] + k % nx[t], j0[t] + k // nx[t]
    cx, cy = px + 0.5, py + 0.5
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    wb = ((cx - a[:, 0]) * (c[:, 1] - a[:, 1]) - (cy - a[:, 1]) * (c[:, 0] - a[:, 0])) / den[t]
    wc = ((b[:, 0] - a[:, 0]) * (cy - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cx - a[:, 0])) / den[t]
    wa = 1 - wb - wc
    eps = -1e-9
    inside = (wa >= eps) & (wb >= eps) & (wc >= eps)
    t, pixel = t[inside], (py * width + px)[inside]
    z = (wa * a[:, 2] + wb * b[:, 2] + wc * c[:, 2])[inside]
    order = np.lexsort((t, -z, pixel))  # by pixel, nearest first, then by triangle
    first = np.unique(pixel[order], return_index=True)[1]
    pixel, z, t = pixel[order][first], z[order][first], t[order][first]
    nearer = z > zbuf[pixel]
    zbuf[pixel[nearer]], face[pixel[nearer]] = z[nearer], t[nearer]


def trace_thin(tri: np.ndarray, face: np.ndarray, zbuf: np.ndarray) -> None:
    """Draws, along their edges, the triangles thinner than a pixel (a needle, a sheet seen edge-on), which
    rasterise's centres can miss over most of their length: a point every pixel step along each edge marks the
    pixel it falls in if rasterise left it empty, nearest first (face, zbuf (height, width), updated in place).
    Pixels rasterise drew keep their triangle: a dense mesh's inside is as rasterise shades it."""
    height, width = face.shape
    a, b, c = tri[:, 0, :2], tri[:, 1, :2], tri[:, 2, :2]
    twice_area = np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    edges = ((0, 1), (1, 2), (2, 0))
    lengths = [np.hypot(*(tri[:, e1, :2] - tri[:, e0, :2]).T) for e0, e1 in edges]  # on screen, per edge
    longest = np.max(lengths, axis=0)
    surface = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 1e-9 * longest**2
    # thin: its least altitude on screen (2 area / longest side) at most a pixel; a surface: not degenerate in 3D (a
    # sheet seen edge-on is one, three points on a line or at one place are not)
    thin = np.nonzero(surface & (twice_area <= longest))[0]
    flat_face, flat_z = face.reshape(-1), zbuf.reshape(-1)
    empty = flat_face < 0
    for (e0, e1), length in zip(edges, lengths, strict=True):
        p, q = tri[thin, e0], tri[thin, e1]
        steps = np.ceil(length[thin]).astype(np.int64) + 1  # points per edge, ends included
        for chunk in np.array_split(np.arange(len(thin)), max(1, int(steps.sum()) // CHUNK_SAMPLES + 1)):
            n = steps[chunk]
            t = np.repeat(chunk, n)
            k = np.arange(len(t)) - np.repeat(np.cumsum(n) - n, n)
            f = (k / np.maximum(steps[t] - 1, 1))[:, None]
            point = p[t] + f * (q[t] - p[t])
            col, row = np.floor(point[:, 0]).astype(np.int64), np.floor(point[:, 1]).astype(np.int64)
            keep = (col >= 0) & (col < width) & (row >= 0) & (row < height)
            pixel, z, owner = (row * width + col)[keep], point[keep, 2], thin[t[keep]]
            order = np.lexsort((owner, -z, pixel))  # by pixel, nearest first, then by triangle
            first = np.unique(pixel[order], return_index=True)[1]
            pixel, z, owner = pixel[order][first], z[order][first], owner[order][first]
            nearer = empty[pixel] & (z > flat_z[pixel])
            flat_z[pixel[nearer]], flat_face[pixel[nearer]] = z[nearer], owner[nearer]


def draw(vertices: np.ndarray, faces: np.ndarray, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """(height, width, 4) uint8 RGBA: the mesh (vertices (n, 3), any unit, +z up; faces (m, 3) int) flat-shaded
    on a transparent background, from AZIMUTH_DEG, ELEVATION_DEG, filling the picture within its margins."""
    axes = view_axes(AZIMUTH_DEG, ELEVATION_DEG)
    s = SUPERSAMPLE
    faces = np.asarray(faces, dtype=np.int64)
    screen = project(vertices, axes, width * s, height * s)
    face, zbuf = rasterise(screen[faces], width * s, height * s)
    trace_thin(screen[faces], face, zbuf)
    shade = face_shades(vertices, faces, axes)
    covered = face >= 0
    rgba = np.zeros((height * s, width * s, 4), dtype=np.float64)
    rgba[covered, :3] = COLOUR * shade[face[covered], None]
    rgba[covered, 3] = 255.0
    # Averaged as premultiplied colour (the background is transparent black), then unpremultiplied.
    rgba = rgba.reshape(height, s, width, s, 4).mean(axis=(1, 3))
    alpha = rgba[..., 3:]
    rgba[..., :3] = np.where(alpha > 0, rgba[..., :3] * 255.0 / np.maximum(alpha, 1e-9), 0.0)
    return np.clip(np.rint(rgba), 0, 255).astype(np.uint8)


def png(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """The thumbnail as PNG bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(draw(vertices, faces), "RGBA").save(buf, format="PNG", optimize=True)
    return buf.getvalue()
