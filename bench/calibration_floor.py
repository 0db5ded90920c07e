"""How far the calibration bench's scenes are from the estimator's prior: the attenuation a clean frame shows by itself.

With range, seasynth.service.calibration.estimate assumes that the statistics of J (the scene's colours in air) do not depend on range.
A scene whose mean colour drifts with range shows an attenuation even through water that attenuates nothing: the
slope of ln(mean J) against range over the estimator's range bins. That apparent attenuation is a floor on beta_D's
error wherever the drift is not seen as such; a beta_D of the same size cannot be measured to 10% in that frame.
"""

from __future__ import annotations

import numpy as np

from seasynth.service.calibration.fit import RANGE_BINS, range_edges

CHANNELS = ("R", "G", "B")


def apparent_attenuation(J: np.ndarray, range_m: np.ndarray, bins: int = RANGE_BINS) -> np.ndarray:
    """(3,) 1/m: minus the least-squares slope of ln(mean J) of each channel against the mean range of `bins`
    equal-count range bins (finite ranges off range edges, as the estimator bins them). J: (h, w, 3) linear;
    range_m: (h, w) metres, +inf open water. NaN for a channel whose mean is 0 in some bin."""
    z = np.asarray(range_m, dtype=np.float64)
    ok = np.isfinite(z) & (z > 0) & ~range_edges(z)
    zf, Jf = z[ok], np.asarray(J, dtype=np.float64)[ok]
    if zf.size < 2 * bins:
        raise ValueError(f"{zf.size} pixels with a usable range; need at least {2 * bins}")
    edges = np.quantile(zf, np.linspace(0, 1, bins + 1))
    b = np.clip(np.searchsorted(edges[1:-1], zf, side="right"), 0, bins - 1)
    count = np.bincount(b, minlength=bins).astype(np.float64)
    keep = count > 0
    zm = np.bincount(b, zf, bins)[keep] / count[keep]
    out = np.full(3, np.nan)
    for c in range(3):
        m = np.bincount(b, Jf[:, c], bins)[keep] / count[keep]
        if (m > 0).all():
            out[c] = -np.polyfit(zm, np.log(m), 1)[0]
    return out


def floor_summary(clean_frames: list[dict], beta_D: dict[str, list[float]]) -> dict:
    """Per water and channel: the median over frames of |apparent attenuation| / beta_D, and how many frames'
    apparent attenuation is under 10% of beta_D. clean_frames: [{"apparent_beta": (3,)}, ...]; beta_D: water ->
    (3,) 1/m."""
    a = np.abs(np.array([f["apparent_beta"] for f in clean_frames], dtype=np.float64))  # (frames, 3)
    out = {}
    for water, bd in beta_D.items():
        share = a / np.asarray(bd, dtype=np.float64)[None, :]
        out[water] = {c: {"median_share": round(float(np.nanmedian(share[:, k])), 3),
                          "frames_under_10pct": f"{int((share[:, k] < 0.1).sum())}/{len(clean_frames)}"}
                      for k, c in enumerate(CHANNELS)}
    return out


def format_floor(result: dict) -> list[str]:
    """Markdown lines: each clean frame's apparent attenuation, and per water the share it makes of beta_D."""
    frames, floor = result["clean_frames"], result["floor"]
    lines = [
        "",
        "## The scenes against the estimator's prior",
        "",
        "The estimator with range assumes that J's statistics do not depend on range. The clean frames' own drift of "
        "mean colour with range, as an attenuation (minus the slope of ln mean J against range over the estimator's "
        "16 range bins; `bench/calibration_floor.py`), is what a photo of each frame through water that attenuates "
        "nothing would show. A beta_D not well above it cannot be measured to 10% in that frame, whatever the fit.",
        "",
        "| scene | frame | range (m) | apparent beta R | G | B (1/m) |",
        "|---|---|---|---|---|---|",
    ]
    for f in frames:
        lo, hi = f["range_m"]
        lines.append(f"| {f['scene']} | {f['frame']} | {lo:.1f}-{hi:.1f} | "
                     + " | ".join(f"{v:+.4f}" for v in f["apparent_beta"]) + " |")
    lines += ["", "Per water: the median over the frames of |apparent beta| / beta_D, and the frames where it is "
              "under 10% (where a 10% beta_D is possible at all).", "",
              "| water | beta_D R / G / B (1/m) | R | G | B |", "|---|---|---|---|---|"]
    for water, per in floor.items():
        bd = result["floor_beta_D"][water]
        lines.append(f"| {water} | {' / '.join(f'{v:.4g}' for v in bd)} | "
                     + " | ".join(f"{per[c]['median_share']:.3g} ({per[c]['frames_under_10pct']})" for c in CHANNELS)
                     + " |")
    return lines
