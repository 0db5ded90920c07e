"""The housing's port and the lens's distortion (spec `camera.port`, `camera.distortion`): every output pixel shows
what its ray in water (seasynth.service.camera_model) meets, resampled from a wider pinhole render.

`prepare` swaps the render for a pinhole at the entrance pupil whose field covers every output pixel's water ray
(plus MARGIN_PX) with pixels no coarser than the output's anywhere (its focal length is 1 / the smallest singular
value of the output's pixel-to-direction Jacobian). `develop` finds, for each output pixel, the point of the wide
render its water ray meets: a water ray starts on the port, not at the pupil (a flat port has no single viewpoint),
so the search is a fixed point along the ray: project the ray's point at the current distance into the wide render,
read the surface's depth there, move to the ray's point at that depth, until no sample moves more than
CONVERGED_PX or PARALLAX_ITERATIONS times (the iterations and the largest last step are recorded). Depth between the wide pixels is interpolated as inverse depth (exact on a plane)
among four neighbours of one instance, else taken from the nearest. Image and clean are then sampled bilinearly in
linear light, instance nearest; range is the distance along the water ray from its origin on the port.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from seasynth.service.camera_model import CameraModel
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.scene import MAX_SIDE, Camera
from seasynth.worker.optics.base import Plain, Shot
from seasynth.worker.render import DrawItem, RenderResult, View, ray_norms

MARGIN_PX = 2  # wide pixels beyond the outermost water ray (bilinear taps and the parallax of near surfaces)
PARALLAX_ITERATIONS = 4
CONVERGED_PX = 1e-4
MAX_OFF_AXIS_DEG = 80.0
NEAREST_PORT_M = 0.1  # the wide field also covers each ray's point this far from the port (nearer surfaces clamp)


@dataclasses.dataclass(frozen=True)
class Rays:
    """A camera's per-pixel water rays and the wide pinhole that covers them."""

    origins: np.ndarray  # (h, w, 3) float64 metres, camera frame; NaN where the ray never reaches the water
    directions: np.ndarray  # (h, w, 3) float64 unit
    K: np.ndarray  # (3, 3) float64: the wide pinhole's intrinsics
    width: int
    height: int
    resolution: float  # the wide pinhole's finest output step, in wide pixels (>= 1 unless MAX_SIDE capped it)
    transmittance: np.ndarray  # (h, w) float32: the port's Fresnel transmittance times (n_air / n_water)^2


@functools.lru_cache(maxsize=8)
def camera_rays(camera: Camera) -> Rays:
    """The water rays of every output pixel centre of `camera` and the wide pinhole covering them."""
    model = CameraModel.from_spec(camera)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    o, d = model.pixel_rays(u, v)
    # A pinhole cannot hold rays at or beyond 90 deg off its axis: those past MAX_OFF_AXIS_DEG are lost (recorded).
    behind = ~(d[..., 2] >= np.cos(np.radians(MAX_OFF_AXIS_DEG)))
    o[behind], d[behind] = np.nan, np.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        q = d[..., :2] / d[..., 2:3]  # normalised pinhole coordinates of each ray's far end
        near = o + NEAREST_PORT_M * d
        q_near = near[..., :2] / near[..., 2:3]
    # The finest output step: the smallest singular value of [dq/du, dq/dv] over the image.
    du, dv = q[:-1, 1:] - q[:-1, :-1], q[1:, :-1] - q[:-1, :-1]
    a, b, c = (du * du).sum(-1), (du * dv).sum(-1), (dv * dv).sum(-1)
    sigma_min = np.sqrt(np.maximum(0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b), 0.0))
    f = 1.0 / np.nanmin(sigma_min)
    pts = np.concatenate([q.reshape(-1, 2), q_near.reshape(-1, 2)])
    lo, hi = np.nanmin(pts, axis=0), np.nanmax(pts, axis=0)
    span = np.max((hi - lo) * f) + 2 * MARGIN_PX + 1
    scale = min(1.0, (MAX_SIDE - 1) / span)  # the renderer's largest side: coarser beyond it (recorded)
    f *= scale
    size = np.ceil((hi - lo) * f + 2 * MARGIN_PX).astype(int) + 1
    K = np.array([[f, 0.0, MARGIN_PX - lo[0] * f], [0.0, f, MARGIN_PX - lo[1] * f], [0.0, 0.0, 1.0]])
    t = np.nan_to_num(model.transmittance(u, v)).astype(np.float32)
    return Rays(origins=o, directions=d, K=K, width=int(size[0]), height=int(size[1]), resolution=scale,
                transmittance=t)


def _project(K: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wide pixel coordinates (qx, qy) of camera-frame points or directions p (..., 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return K[0, 0] * p[..., 0] / p[..., 2] + K[0, 2], K[1, 1] * p[..., 1] / p[..., 2] + K[1, 2]


@dataclasses.dataclass(frozen=True)
class Taps:
    """Where samples at fractional pixels (qx, qy) read an (H, W) image: flat indices into its H * W pixels of each
    sample's top-left tap (clamped so that all four taps lie inside), its weights (fx, fy), (..., 1) float64, and
    the nearest pixel's flat index. NaN positions read pixel 0; positions outside clamp to the edge."""

    corner: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    near: np.ndarray
    width: int

    @classmethod
    def at(cls, qx: np.ndarray, qy: np.ndarray, w: int, h: int) -> Taps:
        qx, qy = np.clip(np.nan_to_num(qx, nan=-1.0), 0, w - 1), np.clip(np.nan_to_num(qy, nan=-1.0), 0, h - 1)
        x0, y0 = np.minimum(np.floor(qx).astype(np.intp), w - 2), np.minimum(np.floor(qy).astype(np.intp), h - 2)
        near = np.rint(qy).astype(np.intp) * w + np.rint(qx).astype(np.intp)
        return cls(corner=y0 * w + x0, fx=(qx - x0)[..., None], fy=(qy - y0)[..., None], near=near, width=w)

    def four(self, image: np.ndarray) -> list[np.ndarray]:
        """image (H, W, ...) at the four taps (top-left, top-right, bottom-left, bottom-right), each (..., C)."""
        flat = image.reshape(image.shape[0] * image.shape[1], -1)
        c, w = self.corner, self.width
        return [flat.take(c + k, axis=0).reshape(*c.shape, -1) for k in (0, 1, w, w + 1)]

    def bilinear(self, image: np.ndarray, four: list[np.ndarray] | None = None) -> np.ndarray:
        """image (H, W, ...) sampled bilinearly, (..., ...) in image's dtype (its taps `four` if already read)."""
        a, b, c, d = self.four(image) if four is None else four
        fx, fy = self.fx, self.fy
        top = a * (1 - fx) + b * fx
        bottom = c * (1 - fx) + d * fx
        return (top * (1 - fy) + bottom * fy).astype(image.dtype).reshape(self.near.shape + image.shape[2:])

    def nearest(self, image: np.ndarray) -> np.ndarray:
        flat = image.reshape(image.shape[0] * image.shape[1], *image.shape[2:])
        return flat.take(self.near, axis=0)


def surface_depth(inv_z: np.ndarray, ids: np.ndarray, taps: Taps) -> np.ndarray:
    """z-depth (metres, +inf where no surface) at fractional wide pixels (their taps): inverse depth interpolated
    bilinearly where the four neighbours show one instance and all hit a surface, else the nearest pixel's."""
    iz4 = taps.four(inv_z)
    near_id = taps.nearest(ids)[..., None]
    same = np.logical_and.reduce([(i == near_id) & (z > 0) for i, z in zip(taps.four(ids), iz4)])[..., 0]
    iz = np.where(same, taps.bilinear(inv_z, iz4), taps.nearest(inv_z))
    with np.errstate(divide="ignore"):
        return 1.0 / iz


class Geometry(Plain):
    name = "geometry"
    shapes_view = True

    def on(self, spec: DatasetSpec) -> bool:
        return not CameraModel.from_spec(spec.camera).pinhole

    def prepare(self, shot: Shot) -> None:
        rays = camera_rays(shot.spec.camera)
        shot.render_view = dataclasses.replace(shot.view, K=rays.K, width=rays.width, height=rays.height)
        shot.needs |= {"ids", "range"}
        shot.float_image = True
        self.samples = None  # (taps, lost): where each output pixel reads the wide render, once developed

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        rays, wide = camera_rays(shot.spec.camera), shot.render_view
        o, d = rays.origins, rays.directions
        qx, qy, t, k, step = search(o, d, wide.K, inverse_depth(wide, result.range_m), result.instance)
        lost = np.isnan(d[..., 0])  # rays that never reach the water: black, no surface
        taps = Taps.at(qx, qy, wide.width, wide.height)
        self.samples = (taps, lost)
        # the camera behind the port records the water's radiance times the port's transmittance (radiance's n^2
        # law across the change of medium, and Fresnel); clean is the frame without water, and keeps the radiance
        image = np.where(lost[..., None], 0.0, taps.bilinear(result.image) * rays.transmittance[..., None])
        image = image.astype(np.float32)
        clean = None if result.clean is None else np.where(
            lost[..., None], 0.0, taps.bilinear(result.clean)).astype(np.float32)
        instance = np.where(lost, 0, taps.nearest(result.instance)).astype(result.instance.dtype)
        range_m = np.where(lost, np.inf, t).astype(np.float32)
        # range / z-depth where the range is a distance (> 0); a surface the port's window touches or the housing
        # would hold (range clamped to 0) takes the pupil ray's norm, so its depth reads 0 (no measurement), not 0/0
        measured = np.isfinite(t) & (t > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            z_out = np.where(measured, o[..., 2] + t * d[..., 2], np.inf)
            shot.range_norms = np.where(measured, t / z_out, 1.0 / d[..., 2]).astype(np.float32)
        finite = step[np.isfinite(step)]
        shot.record[self.name] = {
            "render": {"K": wide.K.tolist(), "width": wide.width, "height": wide.height,
                       "finest_step_px": rays.resolution},
            "parallax_iterations": k,
            "last_step_px_max": float(finite.max()) if finite.size else 0.0,
            "rays_lost": int(lost.sum()),
        }
        return dataclasses.replace(result, image=image, clean=clean, instance=instance, range_m=range_m)

    def pixels_alone(self, shot: Shot, renderer, items: list[DrawItem]) -> list[int]:
        """Each item's output pixels when drawn alone: its wide id render sampled where the frame's pixels were
        (the search's positions for the whole scene), so an item nothing hides counts exactly its visible pixels
        and a hidden one at least them. Where something hides it, its hidden pixels are sampled where the rays met
        the occluder: a ray through a flat port meets the item a little elsewhere (parallax; a pixel of its outline
        may count otherwise)."""
        taps, lost = self.samples
        counts = []
        for item in items:
            ids, _ = renderer.geometry(shot.render_view, [item])
            counts.append(int(np.count_nonzero((taps.nearest(ids) == item.instance_id) & ~lost)))
        return counts


def inverse_depth(wide: View, range_m: np.ndarray) -> np.ndarray:
    """(H, W) float64 1 / z-depth of a wide render's range, 0 where no surface."""
    with np.errstate(divide="ignore"):
        return (ray_norms(wide.K, wide.width, wide.height) / range_m).astype(np.float64)


def search(o: np.ndarray, d: np.ndarray, K: np.ndarray, inv_z: np.ndarray, ids: np.ndarray):
    """Where water rays (origins o, unit directions d, (..., 3)) meet the surfaces of a wide render (intrinsics K,
    inverse depth inv_z, instance ids): the fixed point (module docstring). Returns the wide pixel coordinates
    (qx, qy), the distance t along each ray (+inf where it meets nothing), the iterations and the last step (px)."""
    (ox, oy, oz), (dx, dy, dz) = np.moveaxis(o, -1, 0).copy(), np.moveaxis(d, -1, 0).copy()
    qx, qy = _project(K, d)
    step, k = np.zeros(0), 0
    while True:
        z = surface_depth(inv_z, ids, Taps.at(qx, qy, inv_z.shape[1], inv_z.shape[0]))
        with np.errstate(invalid="ignore"):
            t = np.maximum((z - oz) / dz, 0.0)  # along the water ray to the surface's depth
        if k == PARALLAX_ITERATIONS or (k > 0 and not np.nanmax(step, initial=0.0) > CONVERGED_PX):
            return qx, qy, t, k, step
        far = ~np.isfinite(t)
        t_near = np.where(far, 0.0, t)
        # the ray's point at that distance (its direction where it meets nothing), projected
        px, py, pz = (np.where(far, di, oi + t_near * di) for oi, di in ((ox, dx), (oy, dy), (oz, dz)))
        with np.errstate(divide="ignore", invalid="ignore"):
            nx, ny = K[0, 0] * px / pz + K[0, 2], K[1, 1] * py / pz + K[1, 2]
        step = np.hypot(nx - qx, ny - qy)
        qx, qy, k = nx, ny, k + 1
