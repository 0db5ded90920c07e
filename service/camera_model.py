"""The camera as a function from pixels to rays in water, and back: pinhole intrinsics, Brown-Conrady lens distortion
and the housing's port (flat or dome) refracting by Snell's law. Pure numpy, so users and exports can use it.

Camera frame: KITTI's (x right, y down, z forward), metres, the lens's entrance pupil (the pinhole) at the origin.
Pixels: (u, v) = (column, row), pixel centres at integer coordinates. A pixel's ray leaves the pupil in air with
the direction of its undistorted normalised coordinates (x, y, 1), crosses the port's glass and enters the water at
its origin on the port's outer surface: `pixel_rays` gives that origin and the unit direction in water. Rays that
cannot reach the water (total internal reflection in an off-centre dome, a flat port's ray pointing backwards, a
distortion that does not invert) are NaN in both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seasynth.service.spec.optics import AIR_INDEX
from seasynth.service.spec.scene import Camera

MM = 1e-3
# Undistortion stops where the distortion of the solution is within this of the pixel's normalised coordinates
# (1e-12 of the focal length: ~1e-9 px at f = 1000 px); `project` where the water ray misses the point by this (m).
UNDISTORT_TOL = 1e-12
PROJECT_TOL_M = 1e-10
MAX_ITERATIONS = 50


@dataclass(frozen=True)
class Slab:
    """A flat port as a path tracer builds it: a dielectric slab between the planes z = inner_m and z = outer_m
    (camera frame, normal +z), air (index air_index) before it, water behind it; its sides extend without end."""

    inner_m: float
    outer_m: float
    air_index: float
    glass_index: float
    water_index: float


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics K ((3, 3) float64, pixels), image size, distortion ((5,) float64: k1, k2, p1, p2, k3) and port
    (kind "none", "flat" or "dome"; lengths in metres)."""

    K: np.ndarray
    width: int
    height: int
    distortion: np.ndarray
    kind: str = "none"
    thickness_m: float = 0.0
    glass_index: float = 1.0
    water_index: float = 1.0
    distance_m: float = 0.0  # flat: pupil to the inner plane
    radius_m: float = 0.0  # dome: outer sphere
    centre_m: np.ndarray | None = None  # dome: the spheres' centre in the camera frame (= -pupil offset)

    @classmethod
    def from_spec(cls, camera: Camera) -> CameraModel:
        p = camera.port
        return cls(K=np.asarray(camera.K(), np.float64), width=camera.width, height=camera.height,
                   distortion=np.asarray(camera.distortion, np.float64), kind=p.kind,
                   thickness_m=p.thickness_mm * MM, glass_index=p.glass_index, water_index=p.water_index,
                   distance_m=p.distance_mm * MM, radius_m=p.radius_mm * MM,
                   centre_m=-np.asarray(p.pupil_offset_mm, np.float64) * MM)

    @property
    def pinhole(self) -> bool:
        """No port and no distortion: a pixel's ray is the pinhole's, from the origin."""
        return self.kind == "none" and not self.distortion.any()

    def slab(self) -> Slab:
        """The flat port's slab (path tracers: seasynth.bench.pathtracer)."""
        if self.kind != "flat":
            raise ValueError(f"port kind {self.kind!r} is not a slab (only 'flat' is)")
        return Slab(self.distance_m, self.distance_m + self.thickness_m, AIR_INDEX, self.glass_index,
                    self.water_index)

    def record(self) -> dict:
        """meta's camera model: what `from_record` rebuilds it from."""
        port = {"kind": self.kind}
        if self.kind != "none":
            port.update(thickness_m=self.thickness_m, glass_index=self.glass_index, water_index=self.water_index,
                        air_index=AIR_INDEX)
        if self.kind == "flat":
            port["distance_m"] = self.distance_m
        if self.kind == "dome":
            port.update(radius_m=self.radius_m, centre_m=self.centre_m.tolist())
        return {"K": self.K.tolist(), "width": self.width, "height": self.height,
                "distortion_model": "brown_conrady", "distortion": self.distortion.tolist(), "port": port}

    @classmethod
    def from_record(cls, record: dict) -> CameraModel:
        port = dict(record["port"])
        port.pop("air_index", None)
        kind = port.pop("kind")
        if "centre_m" in port:
            port["centre_m"] = np.asarray(port["centre_m"], np.float64)
        return cls(K=np.asarray(record["K"], np.float64), width=int(record["width"]), height=int(record["height"]),
                   distortion=np.asarray(record["distortion"], np.float64), kind=kind, **port)

    # ---- pixels to rays ----------------------------------------------------------------------------------------
    def air_directions(self, u, v) -> np.ndarray:
        """(..., 3) float64 unit directions in air of pixels (u, v) (arrays of one shape), NaN where the
        distortion does not invert."""
        K = self.K
        xd = (np.asarray(u, np.float64) - K[0, 2]) / K[0, 0]
        yd = (np.asarray(v, np.float64) - K[1, 2]) / K[1, 1]
        x, y = undistort(xd, yd, self.distortion)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_rays(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """(origins, directions), each (..., 3) float64: where pixel (u, v)'s ray enters the water (metres; the
        origin without a port) and its unit direction there; NaN where the ray never reaches the water."""
        return self.water_rays(self.air_directions(u, v))

    def water_rays(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origins, directions) in water of rays leaving the pupil in air with unit directions d (..., 3)."""
        o = np.zeros_like(d)
        if self.kind == "flat":
            return flat_port(d, self.distance_m, self.thickness_m, self.glass_index, self.water_index)
        if self.kind == "dome":
            return dome_port(d, self.centre_m, self.radius_m, self.thickness_m, self.glass_index, self.water_index)
        return o, d

    def housing_points(self, grid: int = 17) -> np.ndarray:
        """(n, 3) float64 metres, camera frame: points of the housing the image looks through, on the rays of a
        grid x grid lattice of the image (edges and corners included) at a quarter, half, three quarters and all of
        their way from the pupil to where they enter the water; (0, 3) without a port."""
        if self.kind == "none":
            return np.zeros((0, 3))
        u, v = np.meshgrid(np.linspace(0.0, self.width, grid), np.linspace(0.0, self.height, grid))
        o, _ = self.pixel_rays(u, v)
        o = o.reshape(-1, 3)
        o = o[np.isfinite(o).all(axis=1)]
        return (np.array([0.25, 0.5, 0.75, 1.0])[:, None, None] * o[None]).reshape(-1, 3)

    def water_clearance(self, points: np.ndarray) -> np.ndarray:
        """(...) float64 metres: how far points (..., 3) (camera frame) lie beyond the port's outer surface, in the
        water (negative: inside the housing or its glass); +inf without a port (the water starts at the pupil)."""
        p = np.asarray(points, np.float64)
        if self.kind == "flat":
            return p[..., 2] - (self.distance_m + self.thickness_m)
        if self.kind == "dome":
            return np.linalg.norm(p - self.centre_m, axis=-1) - self.radius_m
        return np.full(p.shape[:-1], np.inf)

    def transmittance(self, u, v) -> np.ndarray:
        """(...) float64: the share of a water ray's radiance that reaches pixel (u, v) behind the port: the Fresnel
        transmittance (unpolarised) at each of the port's surfaces times (n_air / n_water)^2, radiance's n^2 law
        across the change of medium (the port's inner reflections left out); 1 without a port."""
        d = self.air_directions(u, v)
        if self.kind == "none":
            return np.ones(d.shape[:-1])
        if self.kind == "flat":
            n1 = n2 = np.broadcast_to(np.array([0.0, 0.0, 1.0]), d.shape)
            g = refract(d, -n1, AIR_INDEX, self.glass_index)
        else:
            n1 = (_exit_sphere(np.zeros_like(d), d, self.centre_m, self.radius_m - self.thickness_m) - self.centre_m)
            n1 = n1 / (self.radius_m - self.thickness_m)
            g = refract(d, -n1, AIR_INDEX, self.glass_index)
            p1 = n1 * (self.radius_m - self.thickness_m) + self.centre_m
            n2 = (_exit_sphere(p1, g, self.centre_m, self.radius_m) - self.centre_m) / self.radius_m
        w = refract(g, -n2, self.glass_index, self.water_index)
        t = fresnel_t(d, g, n1, AIR_INDEX, self.glass_index) * fresnel_t(g, w, n2, self.glass_index, self.water_index)
        return t * (AIR_INDEX / self.water_index) ** 2

    # ---- points to pixels --------------------------------------------------------------------------------------
    def project(self, points: np.ndarray) -> np.ndarray:
        """(n, 2) float64 pixels (u, v) where points (n, 3) in water (camera frame, metres) are seen: the pixel
        whose water ray passes through the point (solved by Gauss-Newton on the air direction to PROJECT_TOL_M);
        NaN for points the camera cannot see (behind it, inside the housing, not converged, or beyond the radius
        where the distortion folds back: fold_radius)."""
        P = np.asarray(points, np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / P[:, 2:3]
            xy[P[:, 2] <= 0] = np.nan
            if self.kind != "none":
                xy = self._solve_air(P, xy)
            # Beyond the radius where Brown-Conrady's radial map stops growing it folds back into the image
            if self.distortion.any():
                xy[np.sum(xy * xy, axis=1) >= fold_radius(self.distortion) ** 2] = np.nan
            xd, yd = distort(xy[:, 0], xy[:, 1], self.distortion)
        K = self.K
        return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)

    def _miss(self, P: np.ndarray, xy: np.ndarray, ahead: bool = False) -> np.ndarray:
        """(n, 3): how far the water ray of air slope xy passes from P, perpendicular to the ray (metres); ahead:
        NaN where P lies behind the ray's origin (inside the housing)."""
        d = np.concatenate([xy, np.ones_like(xy[:, :1])], axis=1)
        o, w = self.water_rays(d / np.linalg.norm(d, axis=1, keepdims=True))
        r = P - o
        along = np.sum(r * w, axis=1, keepdims=True)
        miss = r - along * w
        return np.where(along > 0, miss, np.nan) if ahead else miss

    def _solve_air(self, P: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (n, 2) of the air rays whose water rays pass through P (n, 3)."""
        h = 1e-7
        for _ in range(MAX_ITERATIONS):
            e = self._miss(P, xy)
            if not np.nanmax(np.abs(e), initial=0.0) > PROJECT_TOL_M:
                break
            J = np.stack([(self._miss(P, xy + [h, 0.0]) - e) / h, (self._miss(P, xy + [0.0, h]) - e) / h], axis=2)
            JtJ = np.einsum("nki,nkj->nij", J, J)
            step = np.linalg.solve(JtJ + 1e-30 * np.eye(2), np.einsum("nki,nk->ni", J, e)[..., None])[..., 0]
            xy = xy - step
        e = self._miss(P, xy, ahead=True)
        xy[~(np.linalg.norm(e, axis=1) <= 1e3 * PROJECT_TOL_M)] = np.nan
        return xy


# ---- free functions on arrays -----------------------------------------------------------------------------------
def distort(x, y, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brown-Conrady (OpenCV's order k1, k2, p1, p2, k3) of undistorted normalised coordinates."""
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def fold_radius(d: np.ndarray, reach: float = 20.0) -> float:
    """The normalised radius where the radial map r (1 + k1 r^2 + k2 r^4 + k3 r^6) first stops growing (within
    `reach`, to 1e-4 of it), else inf."""
    k1, k2, _, _, k3 = d
    r2 = np.linspace(0.0, reach, 200_001) ** 2
    slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2))
    bad = np.flatnonzero(slope <= 0)
    return float(np.sqrt(r2[bad[0]])) if bad.size else np.inf


def undistort(xd, yd, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates whose distortion is (xd, yd): Newton's method from (xd, yd) until
    every residual is below UNDISTORT_TOL; NaN where it does not converge in MAX_ITERATIONS."""
    xd, yd = np.asarray(xd, np.float64), np.asarray(yd, np.float64)
    if not d.any():
        return xd.copy(), yd.copy()
    k1, k2, p1, p2, k3 = d
    x, y = xd.copy(), yd.copy()
    for _ in range(MAX_ITERATIONS):
        fx, fy = distort(x, y, d)
        ex, ey = fx - xd, fy - yd
        if not np.nanmax(np.abs(np.stack([ex, ey])), initial=0.0) > UNDISTORT_TOL:
            break
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d radial / d r2, times 2 (chain rule on r2 = x^2 + y^2)
        a = radial + x * x * dradial + 2 * p1 * y + 6 * p2 * x  # d fx / dx
        b = x * y * dradial + 2 * p1 * x + 2 * p2 * y  # d fx / dy = d fy / dx
        c = radial + y * y * dradial + 6 * p1 * y + 2 * p2 * x  # d fy / dy
        det = a * c - b * b
        x, y = x - (c * ex - b * ey) / det, y - (a * ey - b * ex) / det
    fx, fy = distort(x, y, d)
    bad = ~(np.maximum(np.abs(fx - xd), np.abs(fy - yd)) <= 1e3 * UNDISTORT_TOL)
    return np.where(bad, np.nan, x), np.where(bad, np.nan, y)


def refract(d: np.ndarray, n: np.ndarray, n1: float, n2: float) -> np.ndarray:
    """Unit directions (..., 3) of unit rays d crossing from index n1 into n2 at surfaces of unit normal n (facing
    the incoming ray: n . d < 0), by Snell's law in vector form; NaN where the ray is totally reflected."""
    eta = n1 / n2
    cos_i = -np.sum(n * d, axis=-1, keepdims=True)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    with np.errstate(invalid="ignore"):
        t = eta * d + (eta * cos_i - np.sqrt(k)) * n
    return np.where(k >= 0, t, np.nan)


def fresnel_t(d: np.ndarray, t: np.ndarray, n: np.ndarray, n1: float, n2: float) -> np.ndarray:
    """(...) unpolarised Fresnel transmittance of unit rays d refracted into t across surfaces of unit normal n
    (either side), from index n1 into n2; NaN where t is (total reflection)."""
    ci, ct = np.abs(np.sum(d * n, axis=-1)), np.abs(np.sum(t * n, axis=-1))
    rs = ((n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)) ** 2
    rp = ((n1 * ct - n2 * ci) / (n1 * ct + n2 * ci)) ** 2
    return 1.0 - 0.5 * (rs + rp)


def flat_port(d: np.ndarray, distance: float, thickness: float, n_glass: float, n_water: float):
    """(origins, directions) in water of air rays from the origin with unit directions d (..., 3) through a slab
    between z = distance and z = distance + thickness (metres); NaN for rays that do not point forwards."""
    with np.errstate(divide="ignore", invalid="ignore"):
        forward = d[..., 2:3] > 0
        normal = np.array([0.0, 0.0, -1.0])
        p1 = d * (distance / d[..., 2:3])
        g = refract(d, normal, AIR_INDEX, n_glass)
        p2 = p1 + g * (thickness / g[..., 2:3])
        w = refract(g, normal, n_glass, n_water)
    return np.where(forward, p2, np.nan), np.where(forward, w, np.nan)


def _exit_sphere(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Points (..., 3) where rays o + s d (s > 0) from inside a sphere leave it."""
    r = o - centre
    b = np.sum(r * d, axis=-1, keepdims=True)
    c = np.sum(r * r, axis=-1, keepdims=True) - radius * radius
    with np.errstate(invalid="ignore"):
        return o + (-b + np.sqrt(b * b - c)) * d


def dome_port(d: np.ndarray, centre: np.ndarray, radius: float, thickness: float, n_glass: float, n_water: float):
    """(origins, directions) in water of air rays from the origin (inside the inner sphere) with unit directions d
    through a spherical shell of outer radius `radius` centred at `centre` (metres); NaN where totally reflected."""
    o = np.zeros_like(d)
    p1 = _exit_sphere(o, d, centre, radius - thickness)
    n1 = (p1 - centre) / (radius - thickness)
    g = refract(d, -n1, AIR_INDEX, n_glass)
    p2 = _exit_sphere(p1, g, centre, radius)
    n2 = (p2 - centre) / radius
    w = refract(g, -n2, n_glass, n_water)
    return np.where(np.isnan(w), np.nan, p2), w
