"""Depth of field: a thin lens's circle of confusion per pixel from its range, applied as a depth-aware gather blur in
linear light (spec `camera.aperture_f`, `camera.focus_m`, `camera.sensor_width_mm`). Geometry does not move: range,
depth, instance ids and labels are the pinhole's."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.lens import Lens
from seasynth.worker.optics.base import Plain, Shot, field_cosine
from seasynth.worker.render import RenderResult, View

# A larger circle of confusion is drawn at this radius: the gather's cost grows with its square (pi R^2 offsets).
MAX_RADIUS_PX = 16
BAND_PIXELS = 65536  # a band of rows summed together: its arrays stay in cache, and it reaches only its own discs


def coc_radius_px(z_m: np.ndarray, fx_px: float, focal_m: float, f_number: float, focus_m: float) -> np.ndarray:
    """(h, w) float32: radius in pixels of the thin lens's circle of confusion for points at z-depth z_m ((h, w)
    metres, +inf where no surface), focused at focus_m. Its diameter on the sensor is A f |z - S| / (z (S - f)) with
    aperture A = f / N; in pixels (pitch f / fx): A fx |1 - S / z| / (S - f), which tends to A fx / (S - f) far away."""
    aperture_m = focal_m / f_number
    with np.errstate(divide="ignore"):
        inv_z = np.where(np.isfinite(z_m), 1.0 / z_m.astype(np.float64), 0.0)
    diameter = aperture_m * fx_px * np.abs(1.0 - focus_m * inv_z) / (focus_m - focal_m)
    return (0.5 * diameter).astype(np.float32)


def gather_blur(images: list[np.ndarray], radius_px: np.ndarray, z_m: np.ndarray) -> list[np.ndarray]:
    """Each (h, w, 3) float32 linear image blurred by the per-pixel discs of radius_px ((h, w) float32 pixels, at most
    MAX_RADIUS_PX), scatter-as-gather: a neighbour s at distance d lends pixel p its light with weight
    coverage(r_s - d) / r_s^2 (its disc's share per pixel; coverage(x) = clip(x + 1/2, 0, 1), an anti-aliased disc
    edge), and a neighbour behind p (z_s > z_p) only inside p's own disc too, so an in-focus foreground edge keeps
    the blurred background off it while a blurred foreground spreads over what lies behind it. Radii at or under
    1/2 px reach no neighbour: where no neighbour lends anything, the pixel keeps its value exactly.

    The sum runs over bands of whole rows (about BAND_PIXELS pixels), each over the offsets its neighbours' largest
    disc reaches and the columns whose neighbours lend anything at that offset: the terms it leaves out are exactly
    0, so the result is the whole image's sum over every offset, term by term in the same order."""
    r = np.minimum(radius_px, MAX_RADIUS_PX).astype(np.float32)
    limit = float(r.max()) + 0.5 if r.size else 0.0  # a disc reaches the offsets d < r + 1/2
    reach = math.ceil(limit) - 1
    if reach <= 0:
        return images
    h, w = r.shape
    pad = ((reach, reach), (reach, reach))
    r_pad = np.pad(r, pad, constant_values=-1.0)  # outside the image: no sample
    area_pad = np.maximum(r_pad, 0.5) ** 2
    z = np.where(np.isfinite(z_m), z_m, np.inf).astype(np.float32)
    z_pad = np.pad(z, pad, constant_values=np.inf)
    # channel planes (3 n, h, w): per-offset products on contiguous rows (a trailing axis of 3 is slow to broadcast)
    planes = np.concatenate([np.moveaxis(im.astype(np.float32, copy=False), -1, 0) for im in images])
    padded = np.pad(planes, ((0, 0), *pad))
    acc = np.zeros_like(planes)
    weight = np.zeros((h, w), np.float32)
    offsets = [(dy, dx, math.hypot(dx, dy)) for dy in range(-reach, reach + 1) for dx in range(-reach, reach + 1)]
    offsets = [(dy, dx, d) for dy, dx, d in offsets if 0 < d < limit]
    rows = max(16, BAND_PIXELS // w)
    for y0 in range(0, h, rows):
        y1 = min(y0 + rows, h)
        col_max = r_pad[y0:y1 + 2 * reach].max(axis=0)  # each padded column's largest radius near the band
        band_limit = float(col_max.max()) + 0.5
        _band(offsets, band_limit, col_max, reach, (y0, y1, w), r[y0:y1], z[y0:y1], r_pad, area_pad, z_pad, padded,
              acc[:, y0:y1], weight[y0:y1])
    lent = weight > 0
    own = 1.0 / np.maximum(r, 0.5) ** 2
    total = own + weight
    out = np.where(lent, (own * planes + acc) / total, planes).astype(np.float32)
    return [np.ascontiguousarray(np.moveaxis(out[3 * k:3 * k + 3], 0, -1)) for k in range(len(images))]


def _band(offsets, band_limit, col_max, reach, rows, r, z, r_pad, area_pad, z_pad, padded, acc, weight) -> None:
    """gather_blur's sum over one band of rows (y0, y1) of an image w wide, into acc (planes) and weight (views)."""
    y0, y1, w = rows
    lend = np.empty(r.shape, np.float32)
    own = np.empty(r.shape, np.float32)
    ahead = np.empty(r.shape, np.float32)
    term = np.empty(r.shape, np.float32)
    for dy, dx, d in offsets:
        if d >= band_limit:
            continue
        # padded columns whose radius reaches offset d (the same float32 sum the terms use: rounding is monotone)
        cols = np.flatnonzero(col_max - d + 0.5 > 0)
        if cols.size == 0:
            continue
        x0, x1 = max(int(cols[0]) - reach - dx, 0), min(int(cols[-1]) + 1 - reach - dx, w)
        if x1 <= x0:
            continue
        src = (slice(reach + y0 + dy, reach + y1 + dy), slice(reach + x0 + dx, reach + x1 + dx))
        n = x1 - x0
        ln, ow, nb, t = lend[:, :n], own[:, :n], ahead[:, :n], term[:, :n]
        np.subtract(r_pad[src], d, out=ln)
        ln += 0.5
        np.clip(ln, 0.0, 1.0, out=ln)
        np.subtract(r[:, x0:x1], d, out=ow)
        ow += 0.5
        np.clip(ow, 0.0, 1.0, out=ow)
        # a neighbour behind lends only inside p's own disc: times own coverage there, times max(own, 1) = 1 elsewhere
        np.less_equal(z_pad[src], z[:, x0:x1], out=nb)
        np.maximum(ow, nb, out=ow)
        ln *= ow
        np.divide(ln, area_pad[src], out=ln)
        weight[:, x0:x1] += ln
        for plane, source in zip(acc, padded):
            np.multiply(ln, source[src], out=t)
            plane[:, x0:x1] += t


class DepthOfField(Plain):
    name = "depth_of_field"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.camera.aperture_f is not None

    def prepare(self, shot: Shot) -> None:
        shot.float_image = True
        shot.needs.add("range")

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        out, shot.record[self.name] = defocused(shot.spec.camera, shot.view, result)
        return out


def defocused(cam: Lens, view: View, result: RenderResult) -> tuple[RenderResult, dict]:
    """The render (its image and clean image; range from its range pass) as the lens `cam` images it from `view`,
    and meta's record of it."""
    fx = float(view.K[0, 0])
    focal_m = cam.focal_length_m(fx, view.width)
    cos_field = field_cosine(view.K, view.width, view.height)
    z = result.range_m * cos_field  # range along the pixel's ray -> depth along the optical axis
    radius = coc_radius_px(z, fx, focal_m, cam.aperture_f, cam.focus_m)
    images = [result.image] + ([] if result.clean is None else [result.clean])
    blurred = gather_blur(images, radius, z)
    record = {"aperture_f": cam.aperture_f, "focus_m": cam.focus_m, "focal_length_mm": focal_m * 1000.0,
              "sensor_width_mm": cam.sensor_width_mm, "max_coc_radius_px": float(radius.max()),
              "radius_cap_px": MAX_RADIUS_PX}
    clean = None if result.clean is None else blurred[1]
    return dataclasses.replace(result, image=blurred[0], clean=clean), record
