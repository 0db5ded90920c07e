"""Second-stage fits behind service.calibration: beta_D refined with the backscatter taken off, the first stage under
a stated Jerlov-family prior, the two stages together, and the refits that size their uncertainty (a range jackknife
and a drift sensitivity). Free functions on service.calibration_fit's records."""

from __future__ import annotations

import numpy as np

from service.calibration_fit import (
    BETA_GRID,
    FINE_POINTS,
    FLAT_SPREAD,
    GROUPS,
    MIN_BIN_PIXELS,
    MIN_BINS,
    RangeData,
    RangeFit,
    fit_range,
    grid_sse,
)
from service.water import JERLOV_TYPES, jerlov_beta


PRIOR_SCALE = np.geomspace(0.25, 4.0, 97)  # family prior: beta_D = s * a member's beta, s on this grid (3% steps)


def fit_range_family(data: RangeData, family: dict[str, np.ndarray]) -> tuple[RangeFit, str]:
    """The first stage under a stated prior: beta_D = s * family[type] (one type and one scale s in PRIOR_SCALE for
    all channels), beta_B_c / beta_D_c within calibration_fit.BACKSCATTER_PRIOR per channel. family: type name ->
    (3,) beta, 1/m. Each channel's SSE is scaled by its own free fit's residual variance, so the channels weigh
    alike. Returns the fit (sigma: the scale's profile width where the scaled SSE <= min + 4, the same relative sigma
    for every channel) and the type ("" when no channel varies with range: then the free fit)."""
    has_open = data.open_pixels >= MIN_BIN_PIXELS
    rows = data.y[0].size
    w2 = float(rows) if has_open else 0.0
    ch = [c for c in range(3) if data.y[c].shape[1] > 0 and np.ptp(data.y[c]) >= FLAT_SPREAD]
    if not ch:  # nothing varies with range: the free fit says so (not identified)
        return fit_range(data), ""
    free = {}
    for c in ch:
        y = data.y[c]
        sse = grid_sse(y, data.h[c], data.z_nodes, BETA_GRID, BETA_GRID, float(data.open_mean[c]), w2, data.drift)[0]
        low = float(sse.min())
        free[c] = (low, max(low / max(rows - GROUPS - 3, 1), (1e-3 * max(float(np.abs(y).max()), 1e-3)) ** 2))
    # Per channel, every member's scaled grid in one least-squares pass (the backscatter's side of the fit is the
    # same for all of them): (members, scales) each of beta_D, the best beta_B, its B_inf and the scaled excess SSE.
    names, n = list(family), PRIOR_SCALE.size
    rows = np.arange(len(names) * n)
    per_channel = {}
    for c in ch:
        bd = np.concatenate([PRIOR_SCALE * family[name][c] for name in names])
        sse, B = grid_sse(data.y[c], data.h[c], data.z_nodes, bd, BETA_GRID, float(data.open_mean[c]), w2, data.drift)
        j = np.argmin(sse, axis=1)
        per_channel[c] = tuple(a.reshape(len(names), n) for a in (
            bd, BETA_GRID[j], B[rows, j], (sse[rows, j] - free[c][0]) / free[c][1]))
    best = (np.inf, "", 0, None)
    totals = {}
    for m, name in enumerate(names):
        total = np.zeros(n)
        for c in ch:
            total += per_channel[c][3][m]
        totals[name] = total
        k = int(np.argmin(total))
        if total[k] < best[0]:
            best = (float(total[k]), name, k, [(c, *(a[m] for a in per_channel[c][:3])) for c in ch])
    score, name, k, per = best
    bd, bb, binf = np.zeros(3), np.zeros(3), data.open_mean.astype(np.float64).copy()
    for c, bdc, bbc, Bc in per:
        bd[c], bb[c], binf[c] = bdc[k], bbc[k], Bc[k]
    for c in set(range(3)) - set(ch):
        bd[c] = PRIOR_SCALE[k] * family[name][c]
        bb[c] = bd[c]
    ok = np.flatnonzero(totals[name] <= score + 4.0)
    rel = float(np.log(PRIOR_SCALE[ok[-1]] / PRIOR_SCALE[ok[0]]) / 4)
    inside = bool(ok[0] > 0 and ok[-1] < PRIOR_SCALE.size - 1)
    in_ch = np.isin(np.arange(3), ch)
    return RangeFit(bd, bb, binf, rel * bd, rel * bb, in_ch & inside, in_ch & inside,
                    np.full(3, has_open) | (in_ch & inside)), name


REFINE_MIN_DIRECT = 0.004  # linear: a bin whose direct signal (mean minus backscatter) is below this is left out


def refine_beta_D(data: RangeData, rf: RangeFit) -> RangeFit:
    """Second stage: with the backscatter of `rf` (beta_B, B_inf) taken off each range bin's mean, fit
    ln(direct) = ln m - ln <exp(-beta_D z)> per channel over BETA_GRID (m in closed form); bins whose direct signal
    is below REFINE_MIN_DIRECT are left out. A channel with fewer than MIN_BINS such bins keeps rf's beta_D, marked
    not inside (too little direct signal to measure its attenuation).

    Why: with the backscatter removed the bin means follow one exponential when J's mean does not depend on range,
    a weaker prior than the first stage's (which also needs beta_D and beta_B apart in one curve)."""
    bd, inside = rf.beta_D.copy(), rf.beta_D_inside.copy()
    for c in range(3):
        if data.y[c].shape[1] == 0:
            continue
        h = data.h[c].mean(axis=0)  # (K, Z): each bin's range distribution (equal-count groups)
        direct = data.y[c].mean(axis=0) - rf.B_inf[c] * (h @ -np.expm1(-rf.beta_B[c] * data.z_nodes))
        ok = direct > REFINE_MIN_DIRECT
        if ok.sum() < MIN_BINS:
            inside[c] = False
            continue
        lt = np.log(np.maximum(data.direct(BETA_GRID) @ h[ok].T, 1e-300))  # (nD, K)
        r = np.log(direct[ok])[None, :] - lt
        sse = ((r - r.mean(axis=1, keepdims=True)) ** 2).sum(axis=1)
        i = int(np.argmin(sse))
        inside[c] &= 0 < i < BETA_GRID.size - 1  # at the grid's end: no minimum found
        fine = np.geomspace(BETA_GRID[max(i - 1, 0)], BETA_GRID[min(i + 1, BETA_GRID.size - 1)], FINE_POINTS)
        lt = np.log(np.maximum(data.direct(fine) @ h[ok].T, 1e-300))
        r = np.log(direct[ok])[None, :] - lt
        bd[c] = fine[int(np.argmin(((r - r.mean(axis=1, keepdims=True)) ** 2).sum(axis=1)))]
    return RangeFit(bd, rf.beta_B, rf.B_inf, rf.beta_D_sigma, rf.beta_B_sigma, inside, rf.beta_B_inside,
                    rf.B_inf_inside)


def fit_two_stage(data: RangeData, prior: str | None) -> tuple[RangeFit, str]:
    """Stage 1 (free, or under the prior) then stage 2; the Jerlov type chosen under the prior, else ""."""
    if prior is None:
        first, name = fit_range(data), ""
    else:
        first, name = fit_range_family(data, {t: jerlov_beta(t) for t in JERLOV_TYPES})
    return refine_beta_D(data, first), name


JACKKNIFE_BLOCKS = 4  # the range jackknife leaves out each quarter of the range bins (contiguous in range) in turn


def range_jackknife(data: RangeData, prior: str | None) -> tuple[np.ndarray, np.ndarray]:
    """Jackknife sigma (3,) of beta_D and beta_B over JACKKNIFE_BLOCKS contiguous blocks of range bins: fits that
    disagree when one range interval is left out show that J's statistics change with range (the prior fails)."""
    block = np.arange(data.bins) * JACKKNIFE_BLOCKS // data.bins
    fits = [fit_two_stage(data.keep_bins(block != b), prior)[0] for b in range(JACKKNIFE_BLOCKS)]
    n = JACKKNIFE_BLOCKS
    jk = lambda a: np.sqrt((n - 1) / n * ((a - a.mean(axis=0)) ** 2).sum(axis=0))  # noqa: E731
    return jk(np.array([f.beta_D for f in fits])), jk(np.array([f.beta_B for f in fits]))


DRIFT_BOUND = 0.1  # the drift sensitivity refits as if J's mean changed by +-10% from the near to the far end


def drift_sensitivity(data: RangeData, prior: str | None, best: RangeFit) -> tuple[np.ndarray, np.ndarray]:
    """(3,) each: the largest change of beta_D and beta_B when the fit assumes that J's mean grows or falls by
    DRIFT_BOUND (log-linear in ln z) across the range instead of staying constant. Where the backscatter or the
    attenuation is small beside such a drift, the data cannot tell them apart, and this says by how much."""
    fits = [fit_two_stage(data.with_drift(sign * np.log1p(DRIFT_BOUND)), prior)[0] for sign in (-1.0, 1.0)]
    return (np.max([np.abs(f.beta_D - best.beta_D) for f in fits], axis=0),
            np.max([np.abs(f.beta_B - best.beta_B) for f in fits], axis=0))
