"""The renderer's water from the solved water column (`column`): the view ray's multiply scattered light as a small
direction table at the camera's depth with its depth rates, and the single scattering attenuated by c on the view leg.

Along a view ray w (z up) from a camera at depth d, with J_ms(w, depth) ~ J_ms(w, d) exp(K_J w_z t) near the camera
(K_J: J_ms's log-rate with depth, one per channel looking down, one looking up), the multiply scattered path
radiance to a range r is

    J_ms(w, d) (1 - exp(-(c - K_J w_z) r)) / (c - K_J w_z)

exact for an exponential column and an infinite ray (r = inf looking level or down; cut at the surface looking up).

The columns are solved once per process at unit sun and unit sky in optical units (c = 1) (`unit_columns`), and
scaled by each channel's c and light.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from seasynth.worker.light import Medium
from seasynth.worker.light.column import Column
from seasynth.worker.light.seabed import exitances, growth_floor, seabed_j
from seasynth.worker.light.sky import MU_SKY, window_radiance
from seasynth.worker.light.unit_columns import (
    NODES_PHI,
    NODES_THETA,
    PHOTONS,
    SEED,
    diffuse_rate,
    quantised,
    reliable_depth,
    unit_column,
)

ED_NODES = 64  # the downwelling irradiance's depth table: ED_NODES nodes from the surface to ED_REACH_M below the
ED_REACH_M = 12.0  # seabed's reference depth (further down: extrapolated from the last two nodes)
# A lamp-lit surface's light is weighted by exp((c - K) r) in the surface pass, so that seen through c it reaches the
# camera as exp(-K r) (its forward-scattered part kept, as the lamps' own model keeps it); the exponent is capped here
# so the weighted radiance stays in the surface target's half floats (past it, where the beam keeps < e^-8 of the
# surface's light, the lamp-lit light is taken as J exp(8 - c r)).
LAMP_SEEN_CAP = 8.0
WINDOW_K = 0.5  # J_ms at the camera is fitted over layers within this many diffuse lengths either side


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
    rates looking down. col: a unit column, its j on the table's nodes (`unit_columns.unit_column`)."""
    reliable = reliable_depth(col, kappa)
    t = min(tau, reliable)
    h = max(WINDOW_K / kappa, 4.0 * col.dz)
    near = (col.z > t - h) & (col.z < max(t + h, h))  # every layer any weight below reaches
    z = col.z[near]
    grid = col.j[near].astype(np.float64)  # (n, NODES_THETA, NODES_PHI)
    k_down = np.clip(_rates(z, grid, t + 0.5 * h, 0.5 * h), 0.0, 1.0)
    k_up = np.clip(_rates(z, grid, max(t - 0.5 * h, 0.5 * h), 0.5 * h), -1.0, 1.0)
    up = (np.arange(NODES_THETA) < (NODES_THETA - 1) // 2)[:, None]  # polar angle below 90 degrees
    dz = (z - t)[:, None, None]
    w = np.maximum(1.0 - np.abs(dz) / h, 0.0)
    back = np.exp(np.where(dz > 0, k_down, k_up) * dz)  # each layer's J brought to depth t
    j = (w * grid * back).sum(axis=0) / max(float(w.sum()) / w.shape[1] / w.shape[2], 1e-300)
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
    seabed_albedo: np.ndarray | None = None  # (3,) the seabed's mean albedo (`seabed`); None: the open column's J_ms
    seabed_depth_m: float = 0.0  # the seabed's mean plane below the surface
    tables: dict = field(default_factory=dict, compare=False, repr=False)  # camera depth -> ViewTable

    def record(self) -> dict:
        """What meta records: each channel's unit columns (b / c, g, the sun's cosine as solved) and the solve's
        photons and seed."""
        seabed = None if self.seabed_albedo is None else {"albedo": [round(float(v), 6) for v in self.seabed_albedo],
                                                          "depth_m": round(self.seabed_depth_m, 6)}
        return {"columns": [list(q) for q in quantised(self.medium, float(self.sun_dir_world[2]))],
                "photons": PHOTONS, "seed": SEED, "seabed": seabed}

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


def _view_table(w: SolvedWater, cam_depth: float, sun: bool, sky: bool) -> ViewTable:
    m = w.medium
    j = np.zeros((NODES_THETA, NODES_PHI, 3))
    k = np.zeros((NODES_THETA, NODES_PHI, 3))
    for ch, (omega, g, mu) in enumerate(quantised(m, float(w.sun_dir_world[2]))):
        c = float(m.c[ch])
        if omega <= 0.0 or c <= 0.0:
            continue
        kappa = diffuse_rate(omega, g)
        sun_col = unit_column(omega, g, mu) if sun and w.sun[ch] > 0 else None
        sky_col = unit_column(omega, g, None) if sky and w.sky[ch] > 0 else None
        parts = [at_depth(col, c * cam_depth, kappa) + (float(scale[ch]),)
                 for col, scale in ((sun_col, w.sun), (sky_col, w.sky)) if col is not None]
        if not parts:
            continue
        if w.seabed_albedo is not None:  # the seabed's light in place of the deep water's below it
            e_d, e_u = exitances(float(w.sun[ch]), float(w.sky[ch]), c * w.seabed_depth_m, kappa, sun_col, sky_col)
            for upwelling, exitance in ((False, float(w.seabed_albedo[ch]) * e_d), (True, -e_u)):
                jb, kb = seabed_j(omega, g, c * (w.seabed_depth_m - cam_depth), kappa, upwelling)
                parts.append((np.repeat(jb[:, None], NODES_PHI, 1), np.repeat(kb[:, None], NODES_PHI, 1), exitance))
        total = sum(s * jp for jp, _, s in parts)
        j[..., ch] = c * np.maximum(total, 0.0)
        # one rate for the sum at each node: the parts' rates weighted by their share of J_ms there
        k[..., ch] = c * np.clip(np.where(total > 0, sum(s * jp * kp for jp, kp, s in parts) / np.where(
            total > 0, total, 1.0), sum(kp for _, kp, _ in parts) / len(parts)), growth_floor()[:, None], 1.0)
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
    reliable = reliable_depth(col, kappa)
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
        kappa = diffuse_rate(omega, g)
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


# The resolve shader's `lookup` (glsl.VOLUME includes it): J_ms and K_J along the unit world direction w. The table is
# a uniform block (`table_block`): as 380 plain vec3 uniforms it passes the compute stage's parameter limit on NVIDIA's
# driver, and a sampler beside the resolve's multisample ones fails validation on Mesa.
VIEW_TABLE_GLSL = f"""
const int NODES_THETA = {NODES_THETA}, NODES_PHI = {NODES_PHI};
layout(std140) uniform ViewTableBlock {{ vec4 u_view_nodes[{2 * NODES_THETA * NODES_PHI}]; }};  // table_block
uniform vec2 u_sun_azimuth;                     // view_azimuth_frame
vec3 node(int i, int k) {{ return u_view_nodes[i * NODES_PHI + k].xyz; }}
void view_table(vec3 w, out vec3 jms, out vec3 kj) {{
    float hn = length(w.xy);
    float cp = hn > 1e-9 ? dot(w.xy, u_sun_azimuth) / hn : 1.0;
    float xt = acos(clamp(w.z, -1.0, 1.0)) * {(NODES_THETA - 1) / math.pi!r};
    float yp = acos(clamp(cp, -1.0, 1.0)) * {(NODES_PHI - 1) / math.pi!r};
    int it = clamp(int(floor(xt)), 0, NODES_THETA - 2), kp = clamp(int(floor(yp)), 0, NODES_PHI - 2);
    float fi = xt - float(it), fk = yp - float(kp);
    jms = mix(mix(node(it, kp), node(it, kp + 1), fk), mix(node(it + 1, kp), node(it + 1, kp + 1), fk), fi);
    int ik = it + NODES_THETA;
    kj = mix(mix(node(ik, kp), node(ik, kp + 1), fk), mix(node(ik + 1, kp), node(ik + 1, kp + 1), fk), fi);
}}
"""


def table_block(table: ViewTable) -> np.ndarray:
    """(2 NODES_THETA NODES_PHI, 4) float32: the view table as the resolve shader's uniform block holds it (std140
    vec4s: the J_ms nodes row by row, then the K_J nodes; w unused)."""
    out = np.zeros((2 * NODES_THETA * NODES_PHI, 4), np.float32)
    out[:, :3] = np.concatenate([table.j, table.k], axis=0).reshape(-1, 3)
    return out


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
                 sky_irradiance: np.ndarray, seabed_albedo: np.ndarray | None = None,
                 seabed_z: float = 0.0) -> SolvedWater:
    """A frame's SolvedWater from its water and its light just below the surface (as PhysicalLight holds them), and
    the seabed's mean albedo and height (world z) where there is one."""
    return SolvedWater(medium=medium, sun_dir_world=np.asarray(sun_dir_world, np.float64),
                       sun=math.pi * np.asarray(sun_irradiance, np.float64), sky=window_radiance(sky_irradiance),
                       seabed_albedo=None if seabed_albedo is None else np.asarray(seabed_albedo, np.float64),
                       seabed_depth_m=max(float(medium.surface_z) - float(seabed_z), 0.0))


def with_column(light, on: bool = True):
    """The PhysicalLight `light` with its water column solved (terms.solved) or, on False, without."""
    if not on:
        return dataclasses.replace(light, column=None, terms=dataclasses.replace(light.terms, solved=False))
    column = solved_water(light.medium, light.sun_dir_world, light.sun_irradiance, light.sky_irradiance,
                          light.seabed_albedo, light.seabed_z)
    return dataclasses.replace(light, column=column, terms=dataclasses.replace(light.terms, solved=True))
