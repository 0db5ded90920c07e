"""The first stage of the range fit under the stated Jerlov-family prior (seasynth.service.calibration.estimate's default with range):
beta_D = s * a Jerlov type's beta for one type and one scale s shared by the channels, and beta_B = r * beta_D with
one ratio r shared by the channels, the parametrisation the generator renders (the spec's water: a type, a jitter
and one backscatter_ratio). Free functions on seasynth.service.calibration.fit's records."""

from __future__ import annotations

import numpy as np

from seasynth.service.calibration.fit import (
    BACKSCATTER_PRIOR,
    BETA_GRID,
    FLAT_SPREAD,
    MIN_BIN_PIXELS,
    RangeData,
    RangeFit,
    fit_range,
    grid_sse,
    profile_width,
    residual_variance,
)

PRIOR_SCALE = np.geomspace(0.25, 4.0, 97)  # beta_D = s * a member's beta, s on this grid (3% steps)
RATIO_GRID = np.geomspace(*(BACKSCATTER_PRIOR or (0.5, 2.0)), 21)  # beta_B / beta_D, shared (7% steps)
FINE_STEPS = 9  # the second pass: this many scales and ratios between the first pass's neighbours
# The prior is rejected, and the free fit used, where its scaled SSE exceeds the free fit's by more than chi-square's
# 0.1% point with 4 degrees of freedom (6 free betas against the prior's scale and ratio): the photo's water is not
# one the prior describes (on the bench's Jerlov waters the excess's 90th percentile is 8.4, chi-square(4)'s 7.8).
PRIOR_REJECT = 18.47


def pair_sse(y: np.ndarray, h: np.ndarray, nodes: np.ndarray, bd: np.ndarray, bb: np.ndarray, y_inf: float,
             w2: float, drift: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """grid_sse's least squares at the pairs (bd[i], bb[i]) instead of a grid: y (G, K), h (G, K, Z), bd and bb (n,)
    1/m. Returns sse (n,) and B (n,), B clipped to [0, 1] as grid_sse clips it."""
    g, k, z = h.shape
    hz = h.reshape(g * k, z).T
    direct = np.exp(-np.outer(bd, nodes))
    t = ((direct if drift is None else direct * drift) @ hz).reshape(-1, g, k)
    u = (-np.expm1(-np.outer(bb, nodes)) @ hz).reshape(-1, g, k)
    stt = np.maximum((t * t).sum(-1), 1e-300)  # (n, G)
    sty = (t * y).sum(-1)
    stu = (t * u).sum(-1)
    a = sty / stt
    yy = ((y * y).sum(-1)[None] - sty * a).sum(-1)  # (n,)
    uy = ((u * y).sum(-1) - stu * a).sum(-1)
    uu = ((u * u).sum(-1) - stu**2 / stt).sum(-1)
    den = uu + w2
    B = np.clip(np.divide(uy + w2 * y_inf, den, out=np.zeros_like(den), where=den > 1e-300), 0.0, 1.0)
    return np.maximum(yy - 2 * B * uy + B**2 * uu + w2 * (y_inf - B) ** 2, 0.0), B


def fit_range_family(data: RangeData, family: dict[str, np.ndarray]) -> tuple[RangeFit, str]:
    """Stage 1 under the family prior: beta_D = s * family[type] and beta_B = r * beta_D, one type, one scale s in
    PRIOR_SCALE and one ratio r in RATIO_GRID for all channels (B_inf and the groups' J per channel, in closed form).
    Each channel's SSE is scaled by its own free fit's residual variance, so the channels weigh alike. A first pass
    on the free fit's beta_B grid (r * beta_D taken at the nearest grid column) chooses the type, s and r; a second
    pass solves exactly at FINE_STEPS x FINE_STEPS scales and ratios between the first's neighbours.

    Returns the fit and the type; "" and the free fit where no channel varies with range (the free fit says so) or
    where the data reject the prior (scaled excess over the free fit above PRIOR_REJECT). sigma:
    the first pass's profile widths where the scaled SSE <= min + 4 (beta_D: the scale's; beta_B: the scale's and
    the ratio's in quadrature), the same relative sigma for every channel; inside: the scale's profile inside its
    grid (beta_B: the ratio's too)."""
    has_open = data.open_pixels >= MIN_BIN_PIXELS
    rows = data.y[0].size
    w2 = float(rows) if has_open else 0.0
    ch = [c for c in range(3) if data.y[c].shape[1] > 0 and np.ptp(data.y[c]) >= FLAT_SPREAD]
    if not ch:
        return fit_range(data), ""
    names, n, nr = list(family), PRIOR_SCALE.size, RATIO_GRID.size
    log_grid = np.log(BETA_GRID)
    step = log_grid[1] - log_grid[0]
    total = np.zeros((len(names) * n, nr))
    scale = {}
    for c in ch:
        y, h, y_inf = data.y[c], data.h[c], float(data.open_mean[c])
        free = grid_sse(y, h, data.z_nodes, BETA_GRID, BETA_GRID, y_inf, w2, data.drift)[0]
        low = float(free.min())
        scale[c] = (low, residual_variance(low, rows, y))
        bd = np.concatenate([PRIOR_SCALE * family[name][c] for name in names])
        sse = grid_sse(y, h, data.z_nodes, bd, BETA_GRID, y_inf, w2, data.drift)[0]
        col = np.clip(np.rint((np.log(np.outer(bd, RATIO_GRID)) - log_grid[0]) / step).astype(np.int64), 0,
                      BETA_GRID.size - 1)
        got = sse[np.arange(bd.size)[:, None], col]  # (members * scales, ratios); +inf outside the ratio band
        total += (np.where(np.isfinite(got), got, 1e30) - low) / scale[c][1]
    best = np.unravel_index(int(np.argmin(total)), total.shape)
    m, k = divmod(int(best[0]), n)
    r = int(best[1])
    by_member = total.reshape(len(names), n, nr)[m]
    threshold = float(total[best]) + 4.0
    rel_s, in_s = profile_width(by_member.min(axis=1), PRIOR_SCALE, threshold)
    rel_r, in_r = profile_width(by_member.min(axis=0), RATIO_GRID, threshold)
    # Second pass: exact pairs around the first pass's choice, for the chosen type.
    fs = np.geomspace(PRIOR_SCALE[max(k - 1, 0)], PRIOR_SCALE[min(k + 1, n - 1)], FINE_STEPS)
    fr = np.geomspace(RATIO_GRID[max(r - 1, 0)], RATIO_GRID[min(r + 1, nr - 1)], FINE_STEPS)
    s_pairs, r_pairs = np.repeat(fs, fr.size), np.tile(fr, fs.size)
    fine, solved = np.zeros(s_pairs.size), {}
    for c in ch:
        bd = s_pairs * family[names[m]][c]
        sse, B = pair_sse(data.y[c], data.h[c], data.z_nodes, bd, r_pairs * bd, float(data.open_mean[c]), w2,
                          data.drift)
        fine += (sse - scale[c][0]) / scale[c][1]
        solved[c] = (bd, r_pairs * bd, B)
    j = int(np.argmin(fine))
    if fine[j] > PRIOR_REJECT:
        return fit_range(data), ""
    bdv, bbv, binf = np.zeros(3), np.zeros(3), data.open_mean.astype(np.float64).copy()
    for c in ch:
        bdv[c], bbv[c], binf[c] = (a[j] for a in solved[c])
    for c in set(range(3)) - set(ch):
        bdv[c] = s_pairs[j] * family[names[m]][c]
        bbv[c] = r_pairs[j] * bdv[c]
    in_d = np.isin(np.arange(3), ch) & in_s
    in_b = in_d & in_r  # a ratio at the prior's bound is the prior's, not the photo's
    return RangeFit(bdv, bbv, binf, rel_s * bdv, float(np.hypot(rel_s, rel_r)) * bbv, in_d, in_b,
                    np.full(3, has_open) | in_d), names[m]
