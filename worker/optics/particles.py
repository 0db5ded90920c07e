"""Marine snow (spec water.particles): a seeded field of small spheres in the volume the camera sees, added to
what the camera draws as one mesh, so the surface shader lights it by the sun, sky and lamps through the water and
the water attenuates it like every surface.

The field is a Poisson process in the camera's view frustum: particles per cubic metre `density`, diameters d from
a power law n(d) ~ d^-slope between the spec's bounds. Only what the frame can show is drawn: a particle of
diameter d is kept out to the depth z_cut(d) where, at full contrast, it would change its pixel by less than
VISIBLE (1/255 of full scale, linear): (pi/4) (d f / z)^2 exp(-k z) = VISIBLE, f the focal length in pixels and k
the least attenuation the water puts on a surface's light (K of the physical model, beta_D of the paper's), so
the cut is where a particle is both well below a pixel and attenuated. Beyond it, particles belong to the
water's own scattering. Where that would draw more than MAX_PARTICLES (a dense field seen at a high resolution),
the threshold rises above VISIBLE, nearest first kept, until the expected count is MAX_PARTICLES: the faintest
particles go first, and meta records the threshold used. Sub-pixel particles contribute through MSAA coverage: each low-poly sphere has the mean
projected area of its sphere, so its expected share of a pixel's samples is the sphere's share of the pixel.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass

import numpy as np
from scipy.special import lambertw

from seasynth.service.camera_model import CameraModel
from seasynth.service.seeds import STREAM_SNOW, frame_rng
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.water import MARINE_SNOW_PER_M3
from seasynth.worker.optics.base import Plain, Shot
from seasynth.worker.render import DrawItem, Mesh, View
from seasynth.worker.scene.sample import Scene

VISIBLE = 1.0 / 255.0  # a particle's least visible share of a pixel at full contrast (linear)
SIZE_BINS = 16  # diameter bins drawn each out to its largest diameter's cut, then thinned to each particle's own
# The most particles a frame draws in expectation (about 100 MB of mesh): past it the visibility threshold rises.
MAX_PARTICLES = 250_000


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """(12, 3) float64 vertices and (20, 3) faces of the icosahedron whose surface area is a unit sphere's (4 pi):
    by Cauchy's formula its mean projected area is then the sphere's (pi)."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array([(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
                  (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)], dtype=np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    f = np.array([(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
                  (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
                  (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)], dtype=np.uint32)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    return v * math.sqrt(4.0 * math.pi / area), f


ICO_VERTICES, ICO_FACES = _icosahedron()


@dataclass(frozen=True)
class Field:
    """One frame's particles, in the camera frame (KITTI axes, metres)."""

    centres: np.ndarray  # (n, 3) float64, metres, camera frame
    diameters: np.ndarray  # (n,) float64, metres
    albedo: np.ndarray  # (n,) float32, linear, the same in R, G and B
    density_per_m3: float
    cut_m: tuple[float, float]  # z_cut of the smallest and the largest diameter, metres
    visible: float = VISIBLE  # the threshold the cut used: VISIBLE, or higher where MAX_PARTICLES bound it

    def record(self, spec_diameter_mm: tuple[float, float], slope: float) -> dict:
        return {"density_per_m3": self.density_per_m3, "diameter_mm": list(spec_diameter_mm), "size_slope": slope,
                "count": len(self.diameters), "cut_m": list(self.cut_m), "visible": self.visible}


def frustum_tans(view: View) -> tuple[float, float, float, float]:
    """x/z and y/z bounds (left, right, top, bottom) of the rays through the image's outer pixel edges."""
    fx, fy, cx, cy = view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2]
    return (-0.5 - cx) / fx, (view.width - 0.5 - cx) / fx, (-0.5 - cy) / fy, (view.height - 0.5 - cy) / fy


def frustum_volume(tans: tuple[float, float, float, float], z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """m^3 of the frustum between depths z0 and z1 (zero where z1 <= z0)."""
    z0, z1 = np.asarray(z0, np.float64), np.asarray(z1, np.float64)
    area = (tans[1] - tans[0]) * (tans[3] - tans[2])
    return area * np.maximum(z1**3 - z0**3, 0.0) / 3.0


def cut_depth(diameter_m: np.ndarray, f_px: float, k: float, far: float, visible: float = VISIBLE) -> np.ndarray:
    """(n,) metres: the depth past which a particle of this diameter changes its pixel by less than `visible`
    (module docstring), at most `far`. k: attenuation (1/m) of a surface's light along the view ray."""
    z0 = np.asarray(diameter_m, np.float64) * f_px * math.sqrt(math.pi / (4.0 * visible))
    x = k * z0 / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):  # z exp(k z / 2) = z0: z = z0 W(x) / x, 1 as x -> 0
        z = z0 * np.where(x > 0, lambertw(x).real / np.where(x > 0, x, 1.0), 1.0)
    return np.minimum(z, far)


def power_law_quantile(u: np.ndarray, lo: float, hi: float, slope: float) -> np.ndarray:
    """Diameters with density ~ d^-slope on [lo, hi] at cumulative probabilities u.

    Computed as log(d / hi) from the ratio lo / hi, never from lo^(1 - slope) itself: that power overflows (or
    divides by zero) for a diameter far below a metre, as a spec's least diameter may be (lo 5e-327 m, or 0)."""
    u = np.asarray(u, np.float64)
    if hi <= lo:
        return np.full(u.shape, lo)
    a = 1.0 - slope
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        log_r = math.log(lo / hi) if lo > 0 else -math.inf  # <= 0
        if abs(a) < 1e-9:  # log-uniform: d = hi (lo / hi)^(1 - u)
            log_d = np.where(u < 1.0, (1.0 - u) * log_r, 0.0)
        elif a > 0:  # d^a = lo^a + u (hi^a - lo^a): (d / hi)^a = 1 - (1 - u) (1 - (lo / hi)^a)
            log_d = np.log1p(-(1.0 - u) * -np.expm1(a * log_r)) / a
        else:  # (d / hi)^a = u + (1 - u) e^L with L = a log(lo / hi) >= 0, in logs where e^L would overflow
            big = a * log_r
            tail = np.where(u < 1.0, np.log1p(-u) + big, -math.inf)
            log_d = np.where(big < 1.0, np.log1p((1.0 - u) * math.expm1(min(big, 1.0))),
                             np.logaddexp(np.log(u), tail)) / a
    return np.where(u <= 0.0, lo, np.clip(hi * np.exp(log_d), lo, hi))  # lo exactly, not hi (lo / hi)


def power_law_cdf(d: np.ndarray, lo: float, hi: float, slope: float) -> np.ndarray:
    """The cumulative probability of power_law_quantile's distribution at d (from ratios, as there)."""
    d = np.asarray(d, np.float64)
    if hi <= lo:
        return np.where(d >= lo, 1.0, 0.0)
    a = 1.0 - slope
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if abs(a) < 1e-9:
            return 1.0 - (math.log(hi) - np.log(d)) / (math.log(hi) - math.log(lo)) if lo > 0 else np.ones(d.shape)
        # F = (d^a - lo^a) / (hi^a - lo^a), as ratios to hi^a (a > 0) or lo^a (a < 0), through expm1
        if a > 0:
            r = math.expm1(a * math.log(lo / hi)) if lo > 0 else -1.0
            return (np.expm1(a * np.log(d / hi)) - r) / -r
        return np.expm1(-a * np.log(lo / d)) / math.expm1(-a * math.log(lo / hi)) if lo > 0 else np.ones(d.shape)


def bin_expectation(tans, f_px: float, edges: np.ndarray, density: float, k: float, view: View,
                    visible: float) -> tuple[np.ndarray, np.ndarray]:
    """Each size bin's depth reach (its largest diameter's cut) and expected count in the frustum out to it."""
    z_bin = cut_depth(edges[1:], f_px, k, view.far, visible)
    return z_bin, density / SIZE_BINS * frustum_volume(tans, view.near, z_bin)


def threshold(tans, f_px: float, edges: np.ndarray, density: float, k: float, view: View) -> float:
    """VISIBLE, or the least threshold (a share of a pixel; above 1, pixels) at which the bins' expected count is at
    most MAX_PARTICLES (bisection in log, to 1e-12 relative)."""
    if bin_expectation(tans, f_px, edges, density, k, view, VISIBLE)[1].sum() <= MAX_PARTICLES:
        return VISIBLE
    lo_v, hi_v = math.log(VISIBLE), math.log(VISIBLE)
    while bin_expectation(tans, f_px, edges, density, k, view, math.exp(hi_v))[1].sum() > MAX_PARTICLES:
        lo_v, hi_v = hi_v, hi_v + 4.0
    while hi_v - lo_v > 1e-12:
        mid = 0.5 * (lo_v + hi_v)
        over = bin_expectation(tans, f_px, edges, density, k, view, math.exp(mid))[1].sum() > MAX_PARTICLES
        lo_v, hi_v = (mid, hi_v) if over else (lo_v, mid)
    return math.exp(hi_v)


def draw_field(rng: np.random.Generator, view: View, density: float, diameter_m: tuple[float, float],
               slope: float, albedo: tuple[float, float], k: float) -> Field:
    """The particles of one frame in `view`'s frustum from its near plane out to each one's cut depth."""
    lo, hi = diameter_m
    tans = frustum_tans(view)
    f_px = float(max(view.K[0, 0], view.K[1, 1]))
    edges = power_law_quantile(np.linspace(0.0, 1.0, SIZE_BINS + 1), lo, hi, slope)

    visible = threshold(tans, f_px, edges, density, k, view)
    z_bin, lam = bin_expectation(tans, f_px, edges, density, k, view, visible)
    counts = rng.poisson(lam)
    n = int(counts.sum())
    bin_of = np.repeat(np.arange(SIZE_BINS), counts)
    u = (bin_of + rng.random(n)) / SIZE_BINS  # equal-probability bins: a uniform draw within the bin's share
    d = power_law_quantile(u, lo, hi, slope)
    z0, z1 = view.near, z_bin[bin_of]
    z = np.cbrt(z0**3 + rng.random(n) * (z1**3 - z0**3))  # density ~ z^2: uniform in the frustum's volume
    x = z * (tans[0] + rng.random(n) * (tans[1] - tans[0]))
    y = z * (tans[2] + rng.random(n) * (tans[3] - tans[2]))
    a = rng.uniform(albedo[0], albedo[1], n).astype(np.float32)
    keep = z <= cut_depth(d, f_px, k, view.far, visible)
    cuts = cut_depth(np.array([lo, hi]), f_px, k, view.far, visible)
    return Field(centres=np.stack([x, y, z], axis=1)[keep], diameters=d[keep], albedo=a[keep],
                 density_per_m3=float(density), cut_m=(float(cuts[0]), float(cuts[1])), visible=visible)


def particle_mesh(field: Field) -> Mesh:
    """The field as one mesh in the camera frame: an icosahedron per particle with its sphere's mean projected
    area, smooth (radial) normals, grey albedo; keyed by its content (uploads are cached by key)."""
    n = len(field.diameters)
    r = (field.diameters / 2.0)[:, None, None]
    vertices = (field.centres[:, None, :] + r * ICO_VERTICES[None]).reshape(-1, 3).astype(np.float32)
    normals = np.broadcast_to(ICO_VERTICES[None], (n, 12, 3)).reshape(-1, 3).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = np.repeat(field.albedo, 12)[:, None].repeat(3, axis=1)
    faces = (ICO_FACES[None] + (12 * np.arange(n, dtype=np.uint32))[:, None, None]).reshape(-1, 3)
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    centre = (lo + hi) / 2.0
    digest = hashlib.sha256(vertices.tobytes() + field.albedo.tobytes()).hexdigest()[:24]
    return Mesh(key=f"particles/{digest}", vertices=vertices, normals=normals, albedo=albedo, faces=faces,
                radius=float(np.linalg.norm(vertices - centre, axis=1).max()), centre=centre)


def surface_attenuation(scene: Scene) -> float:
    """1/m: the least attenuation of a surface's light along a view ray over R, G, B (0 with no water)."""
    if scene.light is not None:
        return float(np.min(scene.light.medium.k))
    if scene.water is not None:
        return float(np.min(scene.water.beta_D))
    return 0.0


def frame_field(spec: DatasetSpec, index: int, scene: Scene, view: View) -> Field:
    """Frame `index`'s particles in `view` (spec water.particles on), from the frame's own marine snow stream: those
    wholly in the water, none inside the housing of a camera behind a port (between its pupil and its window)."""
    p = spec.water.particles
    rng = frame_rng(spec.seed, index, STREAM_SNOW)
    density = float(rng.uniform(*(p.density_per_m3 if p.density_per_m3 is not None
                                  else MARINE_SNOW_PER_M3[scene.water_type])))
    field = draw_field(rng, view, density, (p.diameter_mm[0] / 1e3, p.diameter_mm[1] / 1e3), p.size_slope,
                       p.albedo, surface_attenuation(scene))
    model = CameraModel.from_spec(spec.camera)
    if model.kind == "none":
        return field
    wet = model.water_clearance(field.centres) >= field.diameters / 2.0
    return dataclasses.replace(field, centres=field.centres[wet], diameters=field.diameters[wet],
                               albedo=field.albedo[wet])


class MarineSnow(Plain):
    name = "particles"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.water.enabled and spec.water.particles.enabled

    def prepare(self, shot: Shot) -> None:
        field = frame_field(shot.spec, shot.index, shot.scene, shot.render_view)
        if len(field.diameters):
            shot.items.append(DrawItem(mesh=particle_mesh(field),
                                       world_from_obj=np.linalg.inv(shot.render_view.cam_from_world),
                                       albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32),
                                       instance_id=0, casts_shadows=False))
        p = shot.spec.water.particles
        shot.record[self.name] = field.record(p.diameter_mm, p.size_slope)
