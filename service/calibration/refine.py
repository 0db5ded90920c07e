"""Second-stage fits behind seasynth.service.calibration.estimate: beta_D refined with the backscatter taken off, the two stages
together (stage 1 free, or under the Jerlov-family prior of seasynth.service.calibration.family), and the refits that size
their uncertainty (a range jackknife and a drift sensitivity). Free functions on seasynth.service.calibration.fit's records."""

from __future__ import annotations

import numpy as np

from seasynth.service.calibration.family import fit_range_family
from seasynth.service.calibration.fit import (
    BETA_GRID,
    FINE_POINTS,
    MIN_BINS,
    RangeData,
    RangeFit,
    fit_range,
)
from seasynth.service.water import JERLOV_TYPES, jerlov_beta

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
