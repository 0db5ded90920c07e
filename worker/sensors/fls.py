"""Forward-looking multibeam imaging sonar (FLS): first-hit geometry rendered on the GPU, binned into (range, beam).

The model, stated so it can be checked. It is of the raster family of Stonefish's GPU FLS and Cerqueira et al.'s
rasterised sonar (2017, 2020): range and surface orientation rendered per pixel from the sonar's pose, then binned
by range and beam, then noise; HoloOcean samples an octree and OceanSim casts rays per beam instead.

- Geometry. One perspective render from the sonar's pose covers azimuth |az| <= H/2 and elevation |el| <= V (V the
  vertical -3 dB aperture, so the vertical pattern is sampled to twice its half width), at FLS_STEPS_PER_BEAM pixels
  per beam at the image centre (finer towards the edges). Each pixel centre is one ray: first-hit range r (metres)
  and instance id, so acoustic shadows are exactly the regions a nearer surface hides. No multipath, no water-column
  returns, no sidelobes from outside the rendered aperture, no time smear within the pulse.
- Each pixel is a patch of solid angle dOmega = (1 + x^2 + y^2)^(-3/2) / f^2 (x, y its normalised image
  coordinates) seen at incidence theta (the angle between the ray and the surface normal, from range differences to
  the neighbouring pixels of the same instance; 0 where no neighbour shares it). Its echo intensity is

      e = rho(role) * cos^n(theta) * B_el(el) * dOmega * r^-2 * 10^(-2 alpha r / 10)

  rho: the spec's reflectivity of the seabed, targets or distractors; n = incidence_exponent (n = 1 is Lambert's law:
  backscatter mu cos^2(theta) per unit area times the patch's area r^2 dOmega / cos(theta)); r^-2: two-way
  spherical spreading (r^-4) times the patch's area (r^2 dOmega), so a small facet of fixed size falls as r^-4 and
  an extended seabed per unit solid angle as r^-2; alpha (dB/m) from Francois & Garrison (1982) at the sensor's depth.
- A pixel's echo is spread uniformly over its range footprint (half the range difference to its same-instance
  neighbours on each axis) and split over the range bins it overlaps: a grazing seabed fills every bin, not only the
  bins its pixel centres land in.
- Beams: intensity(bin, beam b) = sum_pixels e * B_az(az - az_b) / Omega_b, Omega_b = sum over all rendered pixels
  of B_az B_el dOmega (the beam's own solid angle), so a perfect reflector filling a beam at normal incidence, all in
  one bin at 1 m, gives 10^(-2 alpha / 10) ~ 1 (full scale at gain 0 dB, no TVG). B is sinc^2 (-3 dB full width:
  beam_width_deg across azimuth, vertical_aperture_deg across elevation; cut at 4 widths) or Gaussian (cut at 2
  widths). Azimuth is taken at the centre of one of 4 sub-bins per beam spacing, or of 3 per beam width for beams
  narrower than 3/4 of their spacing (fine_per_beam), so every beam's pattern is sampled inside its main lobe.
- TVG (on by default) multiplies each bin by r_c^2 10^(2 alpha r_c / 10) at the bin's centre range r_c, then gain.
  Where alpha r / 5 passes TVG_PLAIN_MAX_DECADES within the range window (high frequencies at long range) that
  gain and the echoes' loss leave float64's range, so each pixel's share of a bin takes (r_c / r)^2
  10^(alpha (r_c - r) / 5) instead, in log space (folds_tvg): the same law, finite.
- Speckle and noise (the frame's own FLS stream): out = max(I * S + N, 0), S ~ Gamma(L, 1/L) per cell (unit mean,
  variance 1/L; L = 1 is exponential intensity, i.e. Rayleigh amplitude), N ~ Normal(0, noise_sigma), in full-scale
  units; then 16-bit codes round(min(out, 1) * 65535). Shadows with noise_sigma 0 are exactly 0.

What it leaves out (whatever those simulators do; their beam patterns and noise were not compared here): per-material
acoustic properties (one rho per role: seabed, targets, distractors), sound-speed profiles and refraction, multipath,
water-column and surface returns, pulse shape and range sidelobes, and vehicle motion during a ping. What it adds:
labels (a polar and a fan box per target) and a stated, tested intensity law.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from seasynth.service.spec.sensors import FLS, FLS_STEPS_PER_BEAM, SSS, Acoustics
from seasynth.worker.render import View
from seasynth.worker.scene.poses import rigid_inverse
from seasynth.worker.sensors.fan import fan_geometry, fan_image, label_records

FINE_PER_BEAM = 4  # azimuth sub-bins per beam spacing, at least (fine_per_beam)
TVG_PLAIN_MAX_DECADES = 100.0  # alpha r / 5 at the last bin edge up to which TVG multiplies the bins (folds_tvg)
TVG_MAX_DECADES = 200.0  # a folded TVG share's cap (log10): any share near it is full scale many times over
SINC2_HALF_POWER = 0.4428929  # np.sinc(x)^2 = 0.5 at x = this
FULL_SCALE = 65535


def absorption_db_per_m(frequency_khz: float, water: Acoustics, depth_m: float) -> float:
    """Sound absorption alpha in sea water (dB/m), Francois & Garrison (1982): boric acid, magnesium sulphate and
    pure-water terms at temperature (C), salinity (ppt), pH and depth (m)."""
    T, S, pH, D, f = water.temperature_c, water.salinity_ppt, water.ph, max(depth_m, 0.0), frequency_khz
    c = 1412.0 + 3.21 * T + 1.19 * S + 0.0167 * D
    A1 = 8.86 / c * 10 ** (0.78 * pH - 5)
    f1 = 2.8 * math.sqrt(S / 35) * 10 ** (4 - 1245 / (T + 273))
    A2 = 21.44 * S / c * (1 + 0.025 * T)
    P2 = 1 - 1.37e-4 * D + 6.2e-9 * D * D
    f2 = 8.17 * 10 ** (8 - 1990 / (T + 273)) / (1 + 0.0018 * (S - 35))
    P3 = 1 - 3.83e-5 * D + 4.9e-10 * D * D
    if T <= 20:
        A3 = 4.937e-4 - 2.59e-5 * T + 9.11e-7 * T**2 - 1.5e-8 * T**3
    else:
        A3 = 3.964e-4 - 1.146e-5 * T + 1.45e-7 * T**2 - 6.5e-10 * T**3
    f2_ = f * f
    db_per_km = A1 * f1 * f2_ / (f1 * f1 + f2_) + A2 * P2 * f2 * f2_ / (f2 * f2 + f2_) + A3 * P3 * f2_
    return db_per_km / 1000.0


def beam_pattern(offset_rad: np.ndarray, width_rad: float, kind: str) -> np.ndarray:
    """Two-way intensity pattern B (any shape, float64, 1 on axis, 0.5 at +-width/2), cut to 0 past 4 widths (sinc^2)
    or 2 widths (Gaussian)."""
    x = np.asarray(offset_rad, dtype=np.float64) / width_rad
    if kind == "sinc2":
        return np.where(np.abs(x) <= 4.0, np.sinc(2 * SINC2_HALF_POWER * x) ** 2, 0.0)
    if kind == "gaussian":
        return np.where(np.abs(x) <= 2.0, np.exp(-4 * math.log(2) * x * x), 0.0)
    raise ValueError(f"beam_pattern: unknown kind {kind!r}")


def fine_per_beam(fls: FLS) -> int:
    """Azimuth sub-bins per beam spacing: FINE_PER_BEAM, or FLS_STEPS_PER_BEAM per beam width (as the render's
    pixels) where that is more. Then a sub-bin centre lies within a sixth of a beam width of every beam's axis; at 4
    per spacing a beam narrower than 1/16 (Gaussian) or 1/32 (sinc^2) of its spacing fell between the centres, its
    pattern cut to 0 on all of them, and its weights were 0 / 0."""
    spacing = fls.horizontal_aperture_deg / fls.beams
    return max(FINE_PER_BEAM, math.ceil(FLS_STEPS_PER_BEAM * spacing / fls.beam_width_deg))


@dataclass(frozen=True)
class FlsGrid:
    """The render grid and beamforming of one FLS configuration (a pure function of its spec; cached)."""

    K: np.ndarray  # (3, 3) float64, pixels
    width: int
    height: int
    dirs: np.ndarray  # (h, w, 3) float32, unit ray per pixel, sonar axes (x right, y down, z forward)
    az: np.ndarray  # (h, w) float64, rad, positive to starboard (+x)
    weight: np.ndarray  # (h, w) float64: B_el * dOmega (sr), 0 outside |az| <= H/2, |el| <= V
    fine: np.ndarray  # (h, w) int64, azimuth sub-bin of each pixel
    n_fine: int  # azimuth sub-bins: beams * fine_per_beam
    W: np.ndarray  # (n_fine, beams) float64: B_az(sub-bin centre - beam centre) / Omega_b
    beam_az: np.ndarray  # (beams,) float64, rad, beam centres
    range_edges: np.ndarray  # (range_bins + 1,) float64, metres


@functools.lru_cache(maxsize=8)
def fls_grid(fls: FLS) -> FlsGrid:
    """The FLS's render grid (see FLS.render_size) and per-beam weights."""
    w, h, f = fls.render_size()
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    x = ((np.arange(w) - K[0, 2]) / f)[None, :].repeat(h, 0)
    y = ((np.arange(h) - K[1, 2]) / f)[:, None].repeat(w, 1)
    norm = np.sqrt(1 + x * x + y * y)
    dirs = np.stack([x, y, np.ones_like(x)], axis=-1) / norm[..., None]
    az = np.arctan2(x, 1.0)
    el = np.arctan2(-y, np.sqrt(1 + x * x))
    half_h = math.radians(fls.horizontal_aperture_deg) / 2
    v = math.radians(fls.vertical_aperture_deg)
    inside = (np.abs(az) <= half_h) & (np.abs(el) <= v)
    domega = 1.0 / (f * f * norm**3)
    weight = np.where(inside, beam_pattern(el, v, fls.beam_pattern) * domega, 0.0)
    n_fine = fls.beams * fine_per_beam(fls)
    fine = np.clip(np.floor((az + half_h) / (2 * half_h) * n_fine), 0, n_fine - 1).astype(np.int64)
    fine_az = -half_h + (np.arange(n_fine) + 0.5) * (2 * half_h / n_fine)
    beam_az = -half_h + (np.arange(fls.beams) + 0.5) * (2 * half_h / fls.beams)
    B = beam_pattern(fine_az[:, None] - beam_az[None, :], math.radians(fls.beam_width_deg), fls.beam_pattern)
    omega_fine = np.bincount(fine.ravel(), weights=weight.ravel(), minlength=n_fine)
    omega_beam = omega_fine @ B
    edges = np.linspace(fls.range_m[0], fls.range_m[1], fls.range_bins + 1)
    return FlsGrid(K=K, width=w, height=h, dirs=dirs.astype(np.float32), az=az, weight=weight, fine=fine,
                   n_fine=n_fine, W=B / omega_beam[None, :], beam_az=beam_az, range_edges=edges)


def fls_view(fls: FLS, grid: FlsGrid, world_from_sonar: np.ndarray) -> View:
    """The perspective view the GPU renders for the sonar (near/far bracket its range window)."""
    return View(K=grid.K, width=grid.width, height=grid.height, cam_from_world=rigid_inverse(world_from_sonar),
                near=min(0.05, fls.range_m[0] / 2), far=fls.range_m[1] * 1.01)


def _pair_sum(d: np.ndarray, axis: int) -> np.ndarray:
    """(h, w): each pixel's sum of the pair values d ((h-1, w) or (h, w-1)) of the pairs it belongs to along axis."""
    out = np.zeros(tuple(n + (i == axis) for i, n in enumerate(d.shape)), d.dtype)
    if axis == 0:
        out[1:] += d
        out[:-1] += d
    else:
        out[:, 1:] += d
        out[:, :-1] += d
    return out


def surface_terms(range_m: np.ndarray, instance: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: cos(incidence) (h, w) float32 in [0, 1] and range footprint half-extent (h, w) float32 metres,
    from differences to the 4-neighbours hit on the same instance (their mean where both exist, else the one that
    does; cos 1 and extent 0 where neither does). range_m: (h, w) float32 metres, +inf where no hit; instance: (h, w)
    uint32; dirs: (h, w, 3) float32 unit rays. float32 throughout (the render's ranges are float32)."""
    hit = np.isfinite(range_m)
    r = np.where(hit, range_m, np.float32(0.0)).astype(np.float32)
    P = [dirs[..., k] * r for k in range(3)]
    tangents, half = [], np.zeros(r.shape, np.float32)
    for axis in (0, 1):
        pair = np.diff(instance, axis=axis) == 0
        pair &= np.delete(hit, 0, axis) & np.delete(hit, -1, axis)
        pairf = pair.astype(np.float32)
        n = np.maximum(_pair_sum(pairf, axis), np.float32(1.0))
        tangents.append([_pair_sum(np.diff(Pk, axis=axis) * pairf, axis) / n for Pk in P])
        half += _pair_sum(np.abs(np.diff(r, axis=axis)) * pairf, axis) / n / 2
    (ax, ay, az), (bx, by, bz) = tangents
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    length = np.sqrt(nx * nx + ny * ny + nz * nz)
    dot = np.abs(nx * dirs[..., 0] + ny * dirs[..., 1] + nz * dirs[..., 2])
    ok = length > 0
    cos = np.where(ok, np.minimum(dot / np.where(ok, length, np.float32(1.0)), np.float32(1.0)), np.float32(1.0))
    return np.where(hit, cos, np.float32(0.0)), np.where(hit, half, np.float32(0.0))


def folds_tvg(tvg: bool, alpha_db_per_m: float, edges: np.ndarray) -> bool:
    """Whether TVG is folded into the binning (bin_echoes' tvg_alpha_db_per_m) instead of multiplying the bins: where
    alpha r / 5 at the last bin edge passes TVG_PLAIN_MAX_DECADES, the echoes' 10^(-alpha r / 5) nears float64's
    underflow and the bins' gain 10^(alpha r / 5) its overflow (past ~308 decades it is inf, and inf times an
    empty bin's 0 is NaN)."""
    return tvg and alpha_db_per_m * float(edges[-1]) / 5 > TVG_PLAIN_MAX_DECADES


def bin_echoes(echo: np.ndarray, range_m: np.ndarray, half: np.ndarray, fine: np.ndarray, edges: np.ndarray,
               n_fine: int, tvg_alpha_db_per_m: float | None = None) -> np.ndarray:
    """(range_bins, n_fine) float64: each pixel's echo spread uniformly over [r - half, r + half] and split over the
    range bins it overlaps (all in its bin where half is 0). Pixels with echo 0 add nothing (empty bins stay 0).
    echo, range_m (metres), half (metres): (k,) float64; fine: (k,) int64 azimuth sub-bins; edges: (bins + 1,) m.
    With tvg_alpha_db_per_m (dB/m), echo is without its two-way loss r^-2 10^(-alpha r / 5) and each share of bin
    centre r_c takes TVG over that loss, (r_c / r)^2 10^(alpha (r_c - r) / 5), in log space and at most
    10^TVG_MAX_DECADES: finite at any range (folds_tvg)."""
    nb = len(edges) - 1
    dr = edges[1] - edges[0]
    keep = echo > 0
    e, r, hw, fi = echo[keep], range_m[keep].astype(np.float64), half[keep], fine[keep]
    lo = np.maximum(r - hw, edges[0] - dr)
    hi = np.minimum(r + hw, edges[-1] + dr)
    jl = np.floor((lo - edges[0]) / dr).astype(np.int64)
    jh = np.floor((hi - edges[0]) / dr).astype(np.int64)
    k = jh - jl + 1
    rep = np.repeat(np.arange(len(e)), k)
    j = jl[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(k) - k, k))
    width = (2 * hw)[rep]
    bin_lo, bin_hi = edges[0] + j * dr, edges[0] + (j + 1) * dr
    overlap = np.minimum(r[rep] + hw[rep], bin_hi) - np.maximum(r[rep] - hw[rep], bin_lo)
    frac = np.where(width > 0, np.clip(overlap, 0.0, None) / np.where(width > 0, width, 1.0), 1.0)
    ok = (j >= 0) & (j < nb)
    share = (e[rep] * frac)[ok]
    if tvg_alpha_db_per_m is not None:
        rc, rp, lit = ((edges[:-1] + edges[1:]) / 2)[j[ok]], r[rep][ok], share > 0
        lg = np.log10(np.where(lit, share, 1.0)) + 2 * np.log10(rc / rp) + tvg_alpha_db_per_m * (rc - rp) / 5
        share = np.where(lit, 10 ** np.minimum(lg, TVG_MAX_DECADES), 0.0)
    flat = np.bincount(j[ok] * n_fine + fi[rep][ok], weights=share, minlength=nb * n_fine)
    return flat.reshape(nb, n_fine)


@dataclass(frozen=True)
class FlsEcho:
    intensity: np.ndarray  # (range_bins, beams) float64, full-scale units, after TVG and gain, before speckle/noise
    cell_of: dict[int, np.ndarray]  # instance id -> (k, 2) int64 (bin, beam) cells its pixels' centres fall in
    alpha_db_per_m: float


def pixel_echoes(range_m: np.ndarray, instance: np.ndarray, dirs: np.ndarray, weight: np.ndarray,
                 edges: np.ndarray, reflectivity: np.ndarray, exponent: float, alpha_db_per_m: float,
                 loss: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each rendered pixel's echo before binning, for either sonar: rho cos^n(theta) weight 10^(-2 alpha r/10) r^-2
    (without the last two factors, the two-way loss, when not `loss`: a folded TVG applies them, see bin_echoes).

    range_m (h, w) float32 metres, +inf where no hit; instance (h, w) uint32; dirs and weight: the render grid's
    ray directions and per-pixel weights; edges: range-bin edges (m); reflectivity (max id + 1,) float64 per
    instance id (0 = seabed). Returns inrange (h, w) bool (pixels inside the bins with weight), then per such pixel
    as flat arrays: r float64 m, ids uint32, half float64 (half the range footprint, m), echo float64."""
    inrange = np.isfinite(range_m) & (range_m >= edges[0]) & (range_m < edges[-1]) & (weight > 0)
    cos, half = surface_terms(range_m, instance, dirs)
    r = range_m[inrange].astype(np.float64)
    ids = instance[inrange]
    c = cos[inrange].astype(np.float64)
    rho = reflectivity[np.minimum(ids, len(reflectivity) - 1)]
    echo = rho * (c if exponent == 1 else c**exponent) * weight[inrange]
    if loss:
        echo = echo * 10 ** (-alpha_db_per_m * r / 5) / (r * r)
    return inrange, r, ids, half[inrange].astype(np.float64), echo


def fls_echo(fls: FLS, grid: FlsGrid, range_m: np.ndarray, instance: np.ndarray, reflectivity: np.ndarray,
             alpha_db_per_m: float) -> FlsEcho:
    """The noiseless polar image of one ping from the rendered geometry (range_m (h, w) float32 metres, +inf where
    no hit; instance (h, w) uint32) and reflectivity (max id + 1,) float64 per instance id (0 = seabed)."""
    edges = grid.range_edges
    fold = folds_tvg(fls.tvg, alpha_db_per_m, edges)
    inrange, r, ids, half, echo = pixel_echoes(range_m, instance, grid.dirs, grid.weight, edges, reflectivity,
                                               fls.incidence_exponent, alpha_db_per_m, loss=not fold)
    polar = bin_echoes(echo, r, half, grid.fine[inrange], edges, grid.n_fine, alpha_db_per_m if fold else None)
    polar = polar @ grid.W
    if fls.tvg and not fold:
        rc = (edges[:-1] + edges[1:]) / 2
        polar *= (rc * rc * 10 ** (alpha_db_per_m * rc / 5))[:, None]
    polar *= 10 ** (fls.gain_db / 10)
    # Labels: the (bin, nearest beam) of each labelled pixel centre.
    dr = edges[1] - edges[0]
    spacing = grid.beam_az[1] - grid.beam_az[0]
    bins = np.floor((r - edges[0]) / dr).astype(np.int64)
    beams = np.clip(np.rint((grid.az[inrange] - grid.beam_az[0]) / spacing), 0, fls.beams - 1).astype(np.int64)
    cell_of = {}
    for i in np.unique(ids[ids > 0]):
        m = ids == i
        cell_of[int(i)] = np.unique(np.stack([bins[m], beams[m]], axis=1), axis=0)
    return FlsEcho(intensity=polar, cell_of=cell_of, alpha_db_per_m=alpha_db_per_m)


def speckle_and_noise(intensity: np.ndarray, fls: FLS | SSS, rng: np.random.Generator) -> np.ndarray:
    """max(I * S + N, 0) (same shape, float64): S ~ Gamma(L, 1/L) per cell when fls.speckle, N ~ Normal(0,
    noise_sigma) when noise_sigma > 0. Draws: speckle first (every cell), then noise (every cell)."""
    out = intensity
    if fls.speckle:
        # Gamma(L, 1/L) as numpy draws it, G (1 / L) with G ~ Gamma(L, 1); below L = 5.6e-309 (speckle_looks may be
        # any float > 0) 1 / L is inf: there G / L, which saturates the few cells where G > 0, and a cell with no
        # echo stays 0 (not 0 x inf)
        looks = fls.speckle_looks
        g = rng.standard_gamma(looks, size=intensity.shape)
        with np.errstate(over="ignore"):
            speckle = g * (1.0 / looks) if 1.0 / looks < math.inf else g / looks
        out = np.multiply(out, speckle, out=np.zeros(np.shape(intensity)), where=np.asarray(out) > 0)
    if fls.noise_sigma > 0:
        out = out + rng.normal(0.0, fls.noise_sigma, size=intensity.shape)
    return np.maximum(out, 0.0)


def to_uint16(image: np.ndarray) -> np.ndarray:
    """Full-scale float (any shape) to uint16 codes round(min(v, 1) * 65535)."""
    return np.rint(np.clip(image, 0.0, 1.0) * FULL_SCALE).astype(np.uint16)


@dataclass(frozen=True)
class FlsFrame:
    polar: np.ndarray  # (range_bins, beams) uint16: rows = range bins (nearest first), columns = beams (port first)
    fan: np.ndarray  # (fan height, fan width) uint16 Cartesian fan (seasynth.worker.sensors.fan)
    labels: list[dict]  # seasynth.worker.sensors.fan.label_records
    record: dict  # meta's fls entry


MODEL = ("e = rho * cos^n(incidence) * B_el * dOmega * r^-2 * 10^(-2 alpha r / 10) per rendered pixel, spread over "
         "its range footprint, beamformed with B_az / Omega_b; TVG r^2 10^(2 alpha r / 10); speckle Gamma(L, 1/L) "
         "multiplicative per cell, additive Normal(0, sigma), clipped at 0; alpha Francois-Garrison 1982")


def fls_frame(fls: FLS, acoustics: Acoustics, renderer, items: list, world_from_sonar: np.ndarray,
              objects: dict[int, tuple[str, str | None]], depth_m: float, rng: np.random.Generator) -> FlsFrame:
    """One ping of the sonar at world_from_sonar (4, 4) float64 over the frame's draw items. objects: instance id
    -> (role, class name); depth_m: the sonar's depth below the surface (for alpha); rng: the frame's FLS stream."""
    grid = fls_grid(fls)
    instance, range_m = renderer.geometry(fls_view(fls, grid, world_from_sonar), items)
    rho = {"target": fls.reflectivity_target, "distractor": fls.reflectivity_distractor}
    reflectivity = np.zeros(max(objects, default=0) + 1)
    reflectivity[0] = fls.reflectivity_seabed
    for iid, (role, _) in objects.items():
        reflectivity[iid] = rho[role]
    alpha = absorption_db_per_m(fls.frequency_khz, acoustics, depth_m)
    echo = fls_echo(fls, grid, range_m, instance, reflectivity, alpha)
    polar = to_uint16(speckle_and_noise(echo.intensity, fls, rng))
    fan = fan_geometry(fls)
    record = {
        "model": MODEL,
        "parameters": fls.model_dump(mode="json"),
        "pose_world_from_sonar": world_from_sonar.tolist(),
        "depth_m": depth_m,
        "alpha_db_per_m": alpha,
        "render_size": [grid.width, grid.height],
        "fan_size": [fan.width, fan.height],
        "fan_metres_per_pixel": fan.ds,
        "nonzero_cells": int(np.count_nonzero(polar)),
        "mean_code": float(polar.mean()),
    }
    return FlsFrame(polar=polar, fan=fan_image(polar, fan), labels=label_records(echo.cell_of, objects, fls, fan),
                    record=record)
