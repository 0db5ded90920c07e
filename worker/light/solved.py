"""The renderer's water from the solved water column (`column`): the view ray's multiply scattered light as a small
direction table at the camera's depth with its depth rates, and the single scattering attenuated by c on the view leg.

Along a view ray w (z up) from a camera at depth d, with J_ms(w, depth) ~ J_ms(w, d) exp(K_J w_z t) near the camera
(K_J: J_ms's log-rate with depth, one per channel looking down, one looking up), the multiply scattered path
radiance to a range r is

    J_ms(w, d) (1 - exp(-(c - K_J w_z) r)) / (c - K_J w_z)

exact for an exponential column and an infinite ray (r = inf looking level or down; cut at the surface looking up).

The columns are solved once per process at unit sun and unit sky in optical units (c = 1), for the water's single
scattering albedo b / c, g and the sun's cosine rounded to `OMEGA_STEP`, `G_STEP`, `MU_STEP` (so a frame is the same
function of its spec whichever frames a process rendered before), and scaled by each channel's c and light.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from seasynth import service
from seasynth.worker.light import GORDON_PATH_FACTOR, Medium
from seasynth.worker.light.column import GRID_PHI, GRID_THETA, Column, solve
from seasynth.worker.light.sky import MU_SKY, window_radiance
from seasynth.worker.scene.disk_cache import load_npz, shared_folder, store_npz

ED_NODES = 64  # the downwelling irradiance's depth table: ED_NODES nodes from the surface to ED_REACH_M below the
ED_REACH_M = 12.0  # seabed's reference depth (further down: extrapolated from the last two nodes)
NODES_THETA, NODES_PHI = 19, 10  # the view table: polar angle 0..180 by 10 degrees, azimuth to the sun 0..180 by 20
OMEGA_STEP, G_STEP, MU_STEP = 0.005, 0.01, 0.05
PHOTONS = 20000  # per unit column (one channel, sun or sky)
SEED = 20261129
DEPTHS_K = 12.0  # each unit column reaches this many diffuse lengths 1 / K; the last 4 only feed the ones above
WINDOW_K = 0.5  # J_ms at the camera is fitted over layers within this many diffuse lengths either side


def _diffuse_rate(omega: float, g: float) -> float:
    """K / c of `Medium.k` for a water of single scattering albedo omega (at least 0.02: the column's depth scale)."""
    m = Medium(a=np.array([1.0 - omega]), b=np.array([omega]), g=g, surface_z=0.0)
    return max(float(GORDON_PATH_FACTOR * (1.0 - omega + m.backscatter_fraction * omega)), 0.02)


@functools.lru_cache(maxsize=96)
def unit_column(omega: float, g: float, mu_sun: float | None) -> Column:
    """One channel's column at c = 1: the sun's (unit irradiance normal to the beam at cosine mu_sun) or, mu_sun None,
    the sky's (unit radiance in Snell's window). Seeded, so a pure function of its arguments; kept per process, and
    read from the folder the process shares what it builds in (disk_cache.share_in), where one was stored."""
    folder = shared_folder()
    if folder is None:
        return _solved(omega, g, mu_sun)
    key = repr((service.__version__, "column", omega, g, mu_sun, PHOTONS, SEED, DEPTHS_K))
    path = folder / f"column-{hashlib.sha256(key.encode()).hexdigest()[:32]}.npz"
    got = _load_column(path)
    if got is None:
        got = _solved(omega, g, mu_sun)
        store_npz(path, {f.name: np.asarray(getattr(got, f.name)) for f in dataclasses.fields(Column)})
    return got


def _load_column(path: Path) -> Column | None:
    """The column stored at path; None where there is none or it cannot be read whole (then it is solved again)."""
    return load_npz(path, lambda a: Column(**{f.name: (a[f.name].item() if a[f.name].ndim == 0 else a[f.name])
                                              for f in dataclasses.fields(Column)}))


def _solved(omega: float, g: float, mu_sun: float | None) -> Column:
    z_max = DEPTHS_K / _diffuse_rate(omega, g)
    rng = np.random.default_rng([SEED, round(omega / OMEGA_STEP), round(g / G_STEP), 0 if mu_sun is None
                                 else 1 + round(mu_sun / MU_STEP)])
    if mu_sun is None:
        return solve(1.0 - omega, omega, g, 1.0, 0.0, 1.0, z_max, rng, PHOTONS)
    return solve(1.0 - omega, omega, g, mu_sun, 1.0, 0.0, z_max, rng, PHOTONS)


def _coarse(j: np.ndarray) -> np.ndarray:
    """(..., NODES_THETA, NODES_PHI) box means of (..., GRID_THETA, GRID_PHI) grids about every 4th node (2 either
    side, clipped at the grid's ends)."""
    out = np.empty((*j.shape[:-2], NODES_THETA, NODES_PHI))
    for i in range(NODES_THETA):
        rows = j[..., max(4 * i - 2, 0):min(4 * i + 3, GRID_THETA), :].mean(axis=-2)
        for k in range(NODES_PHI):
            out[..., i, k] = rows[..., max(4 * k - 2, 0):min(4 * k + 3, GRID_PHI)].mean(axis=-1)
    return out


def _rates(z: np.ndarray, j: np.ndarray, centre: float, half: float) -> np.ndarray:
    """(...) -d log j / dz over layers z (n,) of j (n, ...): least squares weighted by a tent of half width `half`
    about `centre` (continuous in both; 0 where fewer than two layers with positive j are in the tent)."""
    w = np.maximum(1.0 - np.abs(z - centre) / half, 0.0)[:, None, None] * (j > 0)
    y = np.log(np.where(j > 0, j, 1.0))
    sw = np.maximum(w.sum(axis=0), 1e-300)
    zc = z[:, None, None] - (w * z[:, None, None]).sum(axis=0) / sw
    yc = y - (w * y).sum(axis=0) / sw
    den = (w * zc * zc).sum(axis=0)
    return np.where(den > 1e-12 * half * half, -(w * zc * yc).sum(axis=0) / np.maximum(den, 1e-300), 0.0)


def at_depth(col: Column, tau: float, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """(J_ms, its rate of decrease with depth), each (NODES_THETA, NODES_PHI), at optical depth tau in the unit
    column's optical units. The rates are fitted over the WINDOW_K diffuse lengths below tau for directions looking
    down or level (clipped to [0, 1]) and above it (not above the surface's first WINDOW_K) for those looking up (to
    [-1, 1]); J_ms is the tent-weighted mean of the layers within WINDOW_K, each brought to tau at its direction's
    rate. Every weight is continuous in tau, so the table is too. Past the column's reliable depth, continued at the
    rates looking down."""
    reliable = col.z[-1] - (DEPTHS_K - 8.0) / kappa
    t = min(tau, reliable)
    h = max(WINDOW_K / kappa, 4.0 * col.dz)
    near = (col.z > t - h) & (col.z < max(t + h, h))  # every layer any weight below reaches
    z = col.z[near]
    coarse = _coarse(col.j[near])  # (n, NODES_THETA, NODES_PHI)
    k_down = np.clip(_rates(z, coarse, t + 0.5 * h, 0.5 * h), 0.0, 1.0)
    k_up = np.clip(_rates(z, coarse, max(t - 0.5 * h, 0.5 * h), 0.5 * h), -1.0, 1.0)
    up = (np.arange(NODES_THETA) < (NODES_THETA - 1) // 2)[:, None]  # polar angle below 90 degrees
    dz = (z - t)[:, None, None]
    w = np.maximum(1.0 - np.abs(dz) / h, 0.0)
    back = np.exp(np.where(dz > 0, k_down, k_up) * dz)  # each layer's J brought to depth t
    j = (w * coarse * back).sum(axis=0) / max(float(w.sum()) / w.shape[1] / w.shape[2], 1e-300)
    return j * np.exp(-k_down * max(tau - reliable, 0.0)), np.where(up, k_up, k_down)


@dataclass(frozen=True)
class ViewTable:
    """What a frame's view rays need at the camera's depth, on the table's nodes (polar angle of w from the zenith,
    azimuth from the sun's vertical plane): j (NODES_THETA, NODES_PHI, 3) float64 J_ms per metre in the renderer's
    radiance units; k (NODES_THETA, NODES_PHI, 3) 1/m its rate of decrease with depth along the node's rays (in
    [0, c] looking level or down, [-c, c] looking up)."""

    j: np.ndarray
    k: np.ndarray


@dataclass(frozen=True)
class DepthTable:
    """The downwelling irradiance on a horizontal surface with depth, node i at i * step_m metres: sun (ED_NODES, 3)
    log of its diffuse part (the solve's E_d less the unscattered beam) over the beam's flux at the surface,
    sky (ED_NODES, 3) log of the sky's E_d over its value at the surface (log 1e-30 where none)."""

    step_m: float
    sun: np.ndarray
    sky: np.ndarray


@dataclass(frozen=True)
class SolvedWater:
    """A frame's water column, solved: the unit columns of each channel and the light that scales them."""

    medium: Medium
    sun_dir_world: np.ndarray  # (3,) towards the refracted sun
    sun: np.ndarray  # (3,) pi x the beam's irradiance normal to it just below the surface (the renderer's units)
    sky: np.ndarray  # (3,) the window's radiance in the renderer's units (`sky.window_radiance`)
    tables: dict = field(default_factory=dict, compare=False, repr=False)  # camera depth -> ViewTable

    def record(self) -> dict:
        """What meta records: each channel's unit columns (b / c, g, the sun's cosine as solved) and the solve's
        photons and seed."""
        return {"columns": [list(q) for q in quantised(self.medium, float(self.sun_dir_world[2]))],
                "photons": PHOTONS, "seed": SEED}

    def depth_table(self) -> DepthTable:
        """The frame's E_d table (one per frame: it spans the seabed's reference depth and ED_REACH_M below)."""
        if "depth" not in self.tables:
            self.tables["depth"] = _depth_table(self)
        return self.tables["depth"]

    def view_table(self, cam_depth: float, sun: bool = True, sky: bool = True) -> ViewTable:
        """The table at a camera depth (metres) of the sun's light, the sky's or both, kept per depth."""
        key = (float(cam_depth), sun, sky)
        if key not in self.tables:
            self.tables[key] = _view_table(self, *key)
        return self.tables[key]


def quantised(medium: Medium, mu_sun: float) -> list[tuple[float, float, float]]:
    """Per channel the (omega, g, mu_sun) its unit columns are solved for."""
    c = medium.c
    omega = np.where(c > 0, medium.b / np.where(c > 0, c, 1.0), 0.0)
    q = lambda v, s: round(round(float(v) / s) * s, 6)
    return [(q(w, OMEGA_STEP), q(medium.g, G_STEP), min(max(q(mu_sun, MU_STEP), MU_STEP), 1.0)) for w in omega]


def _view_table(w: SolvedWater, cam_depth: float, sun: bool, sky: bool) -> ViewTable:
    m = w.medium
    j = np.zeros((NODES_THETA, NODES_PHI, 3))
    k = np.zeros((NODES_THETA, NODES_PHI, 3))
    for ch, (omega, g, mu) in enumerate(quantised(m, float(w.sun_dir_world[2]))):
        c = float(m.c[ch])
        if omega <= 0.0 or c <= 0.0:
            continue
        kappa = _diffuse_rate(omega, g)
        parts = []
        if sun and w.sun[ch] > 0:
            parts.append(at_depth(unit_column(omega, g, mu), c * cam_depth, kappa) + (float(w.sun[ch]),))
        if sky and w.sky[ch] > 0:
            parts.append(at_depth(unit_column(omega, g, None), c * cam_depth, kappa) + (float(w.sky[ch]),))
        if not parts:
            continue
        total = sum(s * jp for jp, _, s in parts)
        j[..., ch] = c * total
        # one rate for the sum at each node: the parts' rates weighted by their share of J_ms there
        k[..., ch] = c * np.where(total > 0, sum(s * jp * kp for jp, kp, s in parts) / np.where(total > 0, total, 1.0),
                                  sum(kp for _, kp, _ in parts) / len(parts))
    return ViewTable(j=j, k=k)


def _log_profile(col: Column, tau: np.ndarray, kappa: float, minus_beam: bool) -> np.ndarray:
    """(n,) log of col.e_d (less its unscattered beam with minus_beam) over its value at the surface, at optical
    depths tau: linear in log between layer centres, from the surface value at 0, continued past the column's
    reliable depth at the log-slope of its last diffuse length there."""
    e = col.e_d.copy()
    top = col.mu_sun * col.e_sun + math.pi * col.sky * (1.0 - math.cos(math.radians(col.cone_deg)) ** 2)
    first = 1.0  # the surface's own value
    if minus_beam:
        edges = np.exp(-np.arange(len(col.z) + 1) * col.dz / col.mu_sun)
        e = e - col.e_sun * col.mu_sun * col.mu_sun / col.dz * (edges[:-1] - edges[1:])  # the layer means `solve` adds
        first = 1e-30
    reliable = col.z[-1] - (DEPTHS_K - 8.0) / kappa
    keep = (col.z <= reliable) & (e > 0)
    z, y = np.concatenate([[0.0], col.z[keep]]), np.log(np.concatenate([[max(first * top, 1e-30)], e[keep]]) / top)
    tail = z >= z[-1] - 1.0 / kappa
    slope = np.polyfit(z[tail], y[tail], 1)[0] if tail.sum() >= 2 else -kappa
    out = np.interp(tau, z, y)
    return np.maximum(np.where(tau > z[-1], y[-1] + min(slope, 0.0) * (tau - z[-1]), out), math.log(1e-30))


def _depth_table(w: SolvedWater) -> DepthTable:
    m = w.medium
    step = (float(m.surface_z) + ED_REACH_M) / (ED_NODES - 1)
    depth = np.arange(ED_NODES) * step
    sun = np.full((ED_NODES, 3), math.log(1e-30))
    sky = np.full((ED_NODES, 3), math.log(1e-30))
    for ch, (omega, g, mu) in enumerate(quantised(m, float(w.sun_dir_world[2]))):
        c = float(m.c[ch])
        if omega <= 0.0 or c <= 0.0:
            sky[:, ch] = -c * depth / MU_SKY  # nothing scattered: today's form
            continue
        kappa = _diffuse_rate(omega, g)
        sun[:, ch] = _log_profile(unit_column(omega, g, mu), c * depth, kappa, True)
        sky[:, ch] = _log_profile(unit_column(omega, g, None), c * depth, kappa, False)
    return DepthTable(step_m=step, sun=sun, sky=sky)


def irradiance(table: DepthTable, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sun's diffuse part, sky's), each (..., 3), of the E_d table at depths (...) metres: exp of the log linearly
    interpolated between nodes, extrapolated past the last from the last two (the surface shader's rule)."""
    x = np.maximum(np.asarray(depth, np.float64), 0.0) / table.step_m
    i = np.clip(np.floor(x), 0, ED_NODES - 2).astype(np.int64)
    f = (x - i)[..., None]
    return tuple(np.exp(t[i] * (1.0 - f) + t[i + 1] * f) for t in (table.sun, table.sky))


# The resolve shader's `lookup` (glsl.VOLUME includes it): J_ms and K_J along the unit world direction w.
VIEW_TABLE_GLSL = f"""
const int NODES_THETA = {NODES_THETA}, NODES_PHI = {NODES_PHI};
uniform vec3 u_jms[{NODES_THETA * NODES_PHI}];   // ViewTable.j, row-major (polar angle, azimuth)
uniform vec3 u_kj[{NODES_THETA * NODES_PHI}];    // ViewTable.k
uniform vec2 u_sun_azimuth;                     // view_azimuth_frame
void view_table(vec3 w, out vec3 jms, out vec3 kj) {{
    float hn = length(w.xy);
    float cp = hn > 1e-9 ? dot(w.xy, u_sun_azimuth) / hn : 1.0;
    float xt = acos(clamp(w.z, -1.0, 1.0)) * {(NODES_THETA - 1) / math.pi!r};
    float yp = acos(clamp(cp, -1.0, 1.0)) * {(NODES_PHI - 1) / math.pi!r};
    int it = clamp(int(floor(xt)), 0, NODES_THETA - 2), kp = clamp(int(floor(yp)), 0, NODES_PHI - 2);
    float fi = xt - float(it), fk = yp - float(kp);
    int n0 = it * NODES_PHI + kp, n1 = n0 + NODES_PHI;
    jms = mix(mix(u_jms[n0], u_jms[n0 + 1], fk), mix(u_jms[n1], u_jms[n1 + 1], fk), fi);
    kj = mix(mix(u_kj[n0], u_kj[n0 + 1], fk), mix(u_kj[n1], u_kj[n1 + 1], fk), fi);
}}
"""


def view_azimuth_frame(sun_dir_world: np.ndarray) -> np.ndarray:
    """(2,) unit horizontal direction of the sun's azimuth ((1, 0) for a sun at the zenith): the table's azimuth 0."""
    h = math.hypot(float(sun_dir_world[0]), float(sun_dir_world[1]))
    return np.array([1.0, 0.0]) if h < 1e-9 else np.asarray(sun_dir_world[:2], np.float64) / h


def lookup(table: ViewTable, dirs_world: np.ndarray, sun_dir_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J_ms, K_J), each (..., 3), along unit world directions (..., 3) by bilinear interpolation in the table (the
    shader's rule:
    polar angle acos(w_z), azimuth acos of w's horizontal part against the sun's, 0 for a vertical w)."""
    s = view_azimuth_frame(sun_dir_world)
    wz = np.clip(dirs_world[..., 2], -1.0, 1.0)
    hx, hy = dirs_world[..., 0], dirs_world[..., 1]
    hn = np.hypot(hx, hy)
    cos_phi = np.where(hn > 1e-9, (hx * s[0] + hy * s[1]) / np.where(hn > 1e-9, hn, 1.0), 1.0)
    x = np.arccos(wz) * ((NODES_THETA - 1) / math.pi)
    y = np.arccos(np.clip(cos_phi, -1.0, 1.0)) * ((NODES_PHI - 1) / math.pi)
    i = np.clip(np.floor(x), 0, NODES_THETA - 2).astype(np.int64)
    k = np.clip(np.floor(y), 0, NODES_PHI - 2).astype(np.int64)
    fi, fk = (x - i)[..., None], (y - k)[..., None]
    return tuple(((t[i, k] * (1 - fk) + t[i, k + 1] * fk) * (1 - fi) + (t[i + 1, k] * (1 - fk) + t[i + 1, k + 1] * fk)
                  * fi) for t in (table.j, table.k))


def solved_water(medium: Medium, sun_dir_world: np.ndarray, sun_irradiance: np.ndarray,
                 sky_irradiance: np.ndarray) -> SolvedWater:
    """A frame's SolvedWater from its water and its light just below the surface (as PhysicalLight holds them)."""
    return SolvedWater(medium=medium, sun_dir_world=np.asarray(sun_dir_world, np.float64),
                       sun=math.pi * np.asarray(sun_irradiance, np.float64), sky=window_radiance(sky_irradiance))


def with_column(light, on: bool = True):
    """The PhysicalLight `light` with its water column solved (terms.solved) or, on False, without."""
    if not on:
        return dataclasses.replace(light, column=None, terms=dataclasses.replace(light.terms, solved=False))
    column = solved_water(light.medium, light.sun_dir_world, light.sun_irradiance, light.sky_irradiance)
    return dataclasses.replace(light, column=column, terms=dataclasses.replace(light.terms, solved=True))
