"""Water estimated from an underwater photo: the revised model's beta_D, beta_B and B_inf, with uncertainties.

Model, per channel c (reference/image-formation.md): I_c = J_c exp(-beta_D_c z) + B_inf_c (1 - exp(-beta_B_c z)),
I in linear light, z the range along the line of sight. Numpy only (the API calls it); the fits live in
service.calibration_fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seasynth.service.calibration import fit, refine
from seasynth.service.errors import CalibrationError
from seasynth.service.water import JERLOV_TYPES, jerlov_beta

CHANNELS = ("R", "G", "B")
MAX_WORK_PIXELS = 250_000  # larger photos are subsampled on a regular grid (every k-th row and column)
MIN_SIDE = 16
DARK_CODE = 10  # an image whose 99th percentile of its brightest channel is below this code is refused
DEFAULT_BOOTSTRAP = 24
# A beta counts as identified when its sigma (bootstrap, profile, range jackknife) is at most this fraction of it
# (and it is off the grid's ends); B_inf when its sigma is at most B_INF_SIGMA_MAX (linear).
BETA_REL_SIGMA_MAX = 0.5
B_INF_SIGMA_MAX = 0.02
SATURATED_SHARE_MAX = 0.01  # of the ranged pixels: above it, B_inf needs open water (see _with_range)

PRIORS = ("jerlov", "none")  # with range; None: DEFAULT_PRIOR with range, none without (that method has its own)
DEFAULT_PRIOR = "jerlov"
METHOD_RANGE = (
    "range: pixels binned by range (16 equal-count bins; pixels on range edges left out); stage 1: each bin split "
    "per channel into 2 equal-count groups (darker and brighter half by their 8 neighbours' mean); each group's mean "
    "follows m_g <exp(-beta_D z)> + B_inf <1 - exp(-beta_B z)> over its pixels' ranges, m_g a constant per group "
    "(prior: the distribution of J does not depend on range), fitted with the open-water pixels (range +inf: they "
    "show B_inf) by least squares over a log grid of beta_D, beta_B with 0.5 <= beta_B / beta_D <= 2 (prior); "
    "stage 2: with stage 1's backscatter taken off, beta_D refitted per channel from ln(bin mean) against range "
    "(prior: the mean of J does not depend on range; bins whose direct signal is below 0.004 linear left out); "
    "sigma: the largest of a bootstrap over image tiles, stage 1's profile width, a range jackknife (the whole fit "
    "repeated leaving out each quarter of the range bins in turn: it grows where J's statistics change with range, "
    "which the priors exclude) and a drift sensitivity (the whole fit repeated assuming J's mean rises or falls by "
    "10% from the nearest to the farthest range); a beta is identified when its sigma is at most half its value and its profile "
    "interval is inside the grid"
)
METHOD_JERLOV = ("; prior jerlov (the default with range): in stage 1, beta_D = s * jerlov_beta(type) for one Jerlov "
                 "type and one scale s in [0.25, 4], and beta_B = r * beta_D for one ratio r in [0.5, 2], both shared "
                 "by the channels (the water the generator renders: a type, a jitter, one backscatter_ratio); stage 2 "
                 "then refits beta_D per channel freely; where the photo rejects the prior (its SSE, scaled by each "
                 "channel's free-fit residual variance, above the free fit's by more than chi-square(4)'s 0.1% point, "
                 "18.5) stage 1 is the free fit")
METHOD_NO_RANGE = (
    "no range: B_inf is the median colour of the flattest 5% of image tiles (prior: open water is the flattest "
    "region); beta_B ratios to green from each tile's darkest pixels, -ln(1 - I_c / B_inf_c) per channel (prior: "
    "the darkest pixels' J is near 0), median over tiles; sigma from a bootstrap over tiles"
)


@dataclass(frozen=True)
class Coefficient:
    """One per-channel quantity (R, G, B). value and sigma are None where it is not identified."""

    name: str
    unit: str
    value: tuple[float | None, float | None, float | None]
    sigma: tuple[float | None, float | None, float | None]
    identified: tuple[bool, bool, bool]
    note: str = ""

    def as_dict(self) -> dict:
        return {"name": self.name, "unit": self.unit, "value": list(self.value), "sigma": list(self.sigma),
                "identified": list(self.identified), "note": self.note}


@dataclass(frozen=True)
class WaterEstimate:
    """What one photo (and its range map, when given) says about the water, and what it cannot say."""

    beta_D: Coefficient  # 1/m, absolute: identified only with range
    beta_B: Coefficient  # 1/m, absolute: identified only with range
    B_inf: Coefficient  # linear RGB
    beta_D_ratio: Coefficient  # beta_D_c / beta_D_G
    beta_B_ratio: Coefficient  # beta_B_c / beta_B_G
    absorption: Coefficient  # a, 1/m: not separable from one image (see note)
    scattering: Coefficient  # b, 1/m: not separable from one image (see note)
    nearest_jerlov: str | None  # the Jerlov type whose beta is closest (log distance, or ratios without range)
    with_range: bool
    method: str
    notes: tuple[str, ...]
    pixels_used: int
    open_water_pixels: int
    range_span_m: tuple[float, float] | None
    bootstrap: int
    seed: int

    def as_dict(self) -> dict:
        coeffs = ("beta_D", "beta_B", "B_inf", "beta_D_ratio", "beta_B_ratio", "absorption", "scattering")
        return {
            **{k: getattr(self, k).as_dict() for k in coeffs},
            "nearest_jerlov": self.nearest_jerlov,
            "with_range": self.with_range,
            "method": self.method,
            "notes": list(self.notes),
            "pixels_used": self.pixels_used,
            "open_water_pixels": self.open_water_pixels,
            "range_span_m": None if self.range_span_m is None else list(self.range_span_m),
            "bootstrap": self.bootstrap,
            "seed": self.seed,
        }


def srgb8_to_linear_table() -> np.ndarray:
    """(256,) float64: linear light of each 8-bit sRGB code (IEC 61966-2-1)."""
    s = np.arange(256) / 255.0
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def half_code(linear: np.ndarray) -> np.ndarray:
    """Half an 8-bit sRGB code's width in linear light at each value: the floor of a B_inf's sigma, since a flat
    region of one code says no more. linear: (3,) -> (3,) float64."""
    v = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    s = np.where(v <= 0.0031308, v * 12.92, 1.055 * np.maximum(v, 0.0031308) ** (1 / 2.4) - 0.055)
    up = np.minimum(s + 0.5 / 255, 1.0)
    return np.abs(np.where(up <= 0.04045, up / 12.92, ((up + 0.055) / 1.055) ** 2.4) - v)


def _check_image(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise CalibrationError(f"image: need (h, w, 3) uint8 sRGB, got {img.shape} {img.dtype}")
    if min(img.shape[:2]) < MIN_SIDE:
        raise CalibrationError(f"image: {img.shape[1]}x{img.shape[0]} is too small; need at least "
                               f"{MIN_SIDE} pixels a side")
    usable = int((img < 255).all(axis=2).sum())
    if usable < max(MIN_SIDE * MIN_SIDE, img.shape[0] * img.shape[1] // 100):
        raise CalibrationError(f"image: only {usable} pixels are below saturation (255) in every channel")
    if np.percentile(img.max(axis=2), 99) < DARK_CODE:
        raise CalibrationError(f"image: too dark to estimate the water (99% of pixels below sRGB code {DARK_CODE})")
    if (img[..., 0] == img[..., 1]).all() and (img[..., 1] == img[..., 2]).all():
        raise CalibrationError("image: it has no colour (its three channels are equal everywhere, e.g. a greyscale "
                               "photo): the water's colour cannot be estimated from it")
    return img


def _check_range(range_m: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float64: metres where finite and > 0, +inf for open water, NaN for no measurement (NaN, <= 0, -inf)."""
    z = np.asarray(range_m)
    if z.shape != shape:
        raise CalibrationError(f"range_m: shape {z.shape} does not match the image's {shape}")
    if not (np.issubdtype(z.dtype, np.floating) or np.issubdtype(z.dtype, np.integer)):
        raise CalibrationError(f"range_m: need a float array in metres, got {z.dtype}")
    z = z.astype(np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~(z > 0)  # NaN, zero, negative, -inf
    return np.where(bad, np.nan, z)


def estimate_water(
    image_srgb8: np.ndarray,
    range_m: np.ndarray | None = None,
    *,
    seed: int = 0,
    bootstrap: int = DEFAULT_BOOTSTRAP,
    max_pixels: int = MAX_WORK_PIXELS,
    prior: str | None = None,
) -> WaterEstimate:
    """Estimate the water of one photo.

    image_srgb8: (h, w, 3) uint8, 8-bit sRGB (decoded to linear light here); pixels with a channel at 255 are left
    out (saturated). range_m: (h, w) float, metres along the line of sight (not z-depth); +inf marks open water
    (no surface: the pixel shows B_inf); NaN, 0 and negatives mark no measurement. None: estimate without range.
    seed: the bootstrap's generator seed (same inputs and seed, same estimate). bootstrap: resamples of image tiles.
    prior: "jerlov" (range only; the default with range): stage 1 takes beta_D from the Jerlov family (a type times a
    scale) and beta_B as one ratio times beta_D, shared by the channels; more accurate on such water, biased off it
    (see the bench's off-family rows). "none": stage 1 fits each channel's beta_D and beta_B freely. None: "jerlov"
    with range; without range neither applies (that method states its own priors).
    Raises CalibrationError naming the input at fault (too small, too dark, no usable range or water).
    """
    img = _check_image(image_srgb8)
    z = None if range_m is None else _check_range(range_m, img.shape[:2])
    if not isinstance(bootstrap, (int, np.integer)) or bootstrap < 2:
        raise CalibrationError(f"bootstrap: need an integer >= 2, got {bootstrap!r}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CalibrationError(f"seed: need an integer >= 0, got {seed!r}")
    if prior is not None and prior not in PRIORS:
        raise CalibrationError(f"prior: need 'jerlov' or 'none' (or none given: the default), got {prior!r}")
    if prior == "jerlov" and z is None:
        raise CalibrationError(f"prior: {prior!r} needs range_m (it constrains the range fit)")
    if not isinstance(max_pixels, (int, np.integer)) or max_pixels < MIN_SIDE * MIN_SIDE:
        raise CalibrationError(f"max_pixels: need an integer >= {MIN_SIDE * MIN_SIDE}, got {max_pixels!r}")
    step = max(1, int(np.ceil(np.sqrt(img.shape[0] * img.shape[1] / max_pixels))))
    img = img[::step, ::step]
    if z is not None:
        z = z[::step, ::step]
    work = fit.Work.build(img, z, srgb8_to_linear_table())
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xCA11]))
    if z is None:
        return _without_range(work, rng, bootstrap, seed)
    chosen = DEFAULT_PRIOR if prior is None else prior
    return _with_range(work, rng, bootstrap, seed, None if chosen == "none" else chosen)


def _coefficient(name: str, unit: str, values: np.ndarray, sigmas: np.ndarray, ok: np.ndarray,
                 note: str = "") -> Coefficient:
    """values, sigmas: (3,) float; ok: (3,) bool. Entries not ok, or not finite, become None."""
    keep = [bool(o) and bool(np.isfinite(v)) and bool(np.isfinite(s)) for v, s, o in zip(values, sigmas, ok)]
    val = tuple(float(v) if k else None for v, k in zip(values, keep))
    sig = tuple(float(s) if k else None for s, k in zip(sigmas, keep))
    return Coefficient(name, unit, val, sig, tuple(keep), note)


def _not_identified(name: str, unit: str, note: str) -> Coefficient:
    return Coefficient(name, unit, (None, None, None), (None, None, None), (False, False, False), note)


_AB_NOTE = ("not identified: absorption and scattering are not separable from beta_D, beta_B and B_inf of one image "
            "(B_inf also carries the unknown illumination); nearest_jerlov names a type whose a, b fit the betas")


def _with_range(work: fit.Work, rng: np.random.Generator, reps: int, seed: int,
                prior: str | None) -> WaterEstimate:
    data = work.range_data()
    if data.bins < fit.MIN_BINS:
        raise CalibrationError(f"range_m: only {data.finite_pixels} pixels have a usable finite range, in "
                               f"{data.bins} bins; need {fit.MIN_BINS} bins of {fit.MIN_BIN_PIXELS} pixels")
    best, family_type = refine.fit_two_stage(data, prior)
    samples = [refine.fit_two_stage(work.range_data(work.resample(rng)), prior)[0] for _ in range(reps)]
    bd = np.array([s.beta_D for s in samples])  # (reps, 3)
    bb = np.array([s.beta_B for s in samples])
    binf = np.array([s.B_inf for s in samples])
    sd = lambda a: np.std(a, axis=0, ddof=1)  # noqa: E731
    jk_d, jk_b = refine.range_jackknife(data, prior)
    dr_d, dr_b = refine.drift_sensitivity(data, prior, best)
    # sigma: the largest of the tile bootstrap's spread, the fit's own profile width (which sees degeneracy), the
    # range jackknife's spread (which sees J's statistics changing with range, the prior's failure) and the drift
    # sensitivity (how far a drift of J's mean with range that the data cannot rule out moves the fit).
    sd_d = np.maximum.reduce([sd(bd), best.beta_D_sigma, jk_d, dr_d])
    sd_b = np.maximum.reduce([sd(bb), best.beta_B_sigma, jk_b, dr_b])
    ok_d = best.beta_D_inside & (sd_d <= BETA_REL_SIGMA_MAX * best.beta_D)
    ok_b = best.beta_B_inside & (sd_b <= BETA_REL_SIGMA_MAX * best.beta_B)
    sd_inf = np.maximum(sd(binf), half_code(best.B_inf))
    # B_inf is seen in open water, or is the asymptote of an identified backscatter; a value the fit clipped to 0 or
    # 1 is a bound, not an estimate. With saturated surfaces left out, the asymptote is biased (the bright near
    # pixels are missing from the fit, several sigma in tests): then only open water identifies it.
    open_water = data.open_pixels >= fit.MIN_BIN_PIXELS
    clipped = work.saturated_share > SATURATED_SHARE_MAX
    at_bound = (best.B_inf <= 0.0) | (best.B_inf >= 1.0)
    seen = open_water | (ok_b & (not clipped))  # (3,): in open water, or as an identified, unbiased asymptote
    ok_inf = best.B_inf_inside & seen & ~at_bound & (sd_inf <= B_INF_SIGMA_MAX)
    notes = []
    for c, name in enumerate(CHANNELS):
        if not ok_d[c]:
            notes.append(f"beta_D {name}: not identified (range span or contrast too small for this channel, or "
                         "the fit changes when a range interval is left out)")
        if not ok_b[c]:
            notes.append(f"beta_B {name}: not identified (too little backscatter against noise and scene variation "
                         "in this channel)")
        if not ok_inf[c]:
            if at_bound[c]:
                why = f"the fit clipped it to {0 if best.B_inf[c] <= 0.0 else 1}"
            elif seen[c]:
                why = f"its sigma is over {B_INF_SIGMA_MAX} or its profile leaves the grid"
            else:
                why = ("no open water, and the backscatter's asymptote is not identified"
                       + (" or is biased by saturated pixels" if clipped else ""))
            notes.append(f"B_inf {name}: not identified ({why})")
    if not open_water:
        notes.append("no open water (range +inf) in view: B_inf comes from the fit's asymptote alone")
    if clipped:
        notes.append(f"{work.saturated_share:.1%} of the pixels with range are saturated (a channel at 255) and left "
                     "out: the brightest surfaces are missing from the fit; expose so that under "
                     f"{SATURATED_SHARE_MAX:.0%} clip")
    if prior is not None and family_type:
        notes.append(f"prior {prior}: stage 1 chose Jerlov type {family_type}; off the Jerlov family (or with a "
                     "backscatter ratio that differs by channel) this prior biases the estimate; prior none fits each "
                     "channel freely")
    elif prior is not None:
        notes.append(f"prior {prior}: not used: this photo rejects it (its fit is worse than each channel's free fit "
                     "by more than chance allows), or no channel varies with range; stage 1 is the free fit")
    ratio_d, ratio_d_sd = _ratios(best.beta_D, bd)
    ratio_b, ratio_b_sd = _ratios(best.beta_B, bb)
    beta_D = _coefficient("beta_D", "1/m", best.beta_D, sd_d, ok_d)
    return WaterEstimate(
        beta_D=beta_D,
        beta_B=_coefficient("beta_B", "1/m", best.beta_B, sd_b, ok_b),
        B_inf=_coefficient("B_inf", "linear", best.B_inf, sd_inf, ok_inf),
        beta_D_ratio=_coefficient("beta_D_ratio", "1", ratio_d, ratio_d_sd, ok_d & ok_d[1]),
        beta_B_ratio=_coefficient("beta_B_ratio", "1", ratio_b, ratio_b_sd, ok_b & ok_b[1]),
        absorption=_not_identified("absorption", "1/m", _AB_NOTE),
        scattering=_not_identified("scattering", "1/m", _AB_NOTE),
        nearest_jerlov=_nearest_jerlov(beta_D, ratios=False),
        with_range=True,
        method=METHOD_RANGE + (METHOD_JERLOV if prior == "jerlov" else ""),
        notes=tuple(notes),
        pixels_used=data.finite_pixels + data.open_pixels,
        open_water_pixels=data.open_pixels,
        range_span_m=(round(float(data.z_lo), 4), round(float(data.z_hi), 4)),
        bootstrap=reps,
        seed=seed,
    )


def _ratios(best: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ratios to green of a (3,) estimate and their bootstrap sigma from (reps, 3) samples (NaN where undefined)."""
    r = np.divide(best, best[1], out=np.full(3, np.nan), where=best[1] > 0)
    rs = np.divide(samples, samples[:, 1:2], out=np.full(samples.shape, np.nan), where=samples[:, 1:2] > 0)
    return r, _finite_std(rs)


def _finite_std(a: np.ndarray) -> np.ndarray:
    """(reps, 3) -> (3,): each column's sample std over its finite entries; NaN with fewer than 2."""
    out = np.full(a.shape[1], np.nan)
    for c in range(a.shape[1]):
        got = a[np.isfinite(a[:, c]), c]
        if got.size > 1:
            out[c] = np.std(got, ddof=1)
    return out


def _without_range(work: fit.Work, rng: np.random.Generator, reps: int, seed: int) -> WaterEstimate:
    stats = work.tile_data()
    best = fit.fit_no_range(stats)
    samples = [fit.fit_no_range(stats, work.resample_tiles(rng)) for _ in range(reps)]
    binf = np.array([s.B_inf for s in samples])
    ratio = np.array([s.beta_B_ratio for s in samples])
    binf_sd = np.maximum(np.std(binf, axis=0, ddof=1), half_code(best.B_inf))
    ratio_sd = _finite_std(ratio)
    ok_inf = (binf_sd <= B_INF_SIGMA_MAX) & best.water_flat
    ok_ratio = np.isfinite(best.beta_B_ratio) & (ratio_sd <= BETA_REL_SIGMA_MAX * np.abs(best.beta_B_ratio))
    ok_ratio &= ok_ratio[1]
    notes = ["beta_D and beta_B in 1/m: not identified without range (only their ratios between channels could be)",
             "beta_D ratios: not identified without range (they need J, which this prior-based method does not "
             "estimate)"]
    if not best.water_flat:
        notes.append("B_inf: not identified: no flat open-water region found (the flattest region's colour would be "
                     "a guess)")
    for c, name in enumerate(CHANNELS):
        if best.water_flat and not ok_inf[c]:
            notes.append(f"B_inf {name}: not identified (the flattest tiles disagree by more than "
                         f"{B_INF_SIGMA_MAX} linear)")
        if c != 1 and not ok_ratio[c]:
            notes.append(f"beta_B ratio {name}/G: not identified ({best.dark_tiles} tiles with usable dark pixels"
                         + (", and green's own is not" if not ok_ratio[1] else "") + ")")
    beta_B_ratio = _coefficient("beta_B_ratio", "1", best.beta_B_ratio, ratio_sd, ok_ratio,
                                "prior: the darkest pixels of a tile have J near 0")
    return WaterEstimate(
        beta_D=_not_identified("beta_D", "1/m", "not identified without range"),
        beta_B=_not_identified("beta_B", "1/m", "not identified without range"),
        B_inf=_coefficient("B_inf", "linear", best.B_inf, binf_sd, ok_inf,
                           "prior: open water is the flattest region of the image"),
        beta_D_ratio=_not_identified("beta_D_ratio", "1", "not identified without range"),
        beta_B_ratio=beta_B_ratio,
        absorption=_not_identified("absorption", "1/m", _AB_NOTE),
        scattering=_not_identified("scattering", "1/m", _AB_NOTE),
        nearest_jerlov=_nearest_jerlov(beta_B_ratio, ratios=True),
        with_range=False,
        method=METHOD_NO_RANGE,
        notes=tuple(notes),
        pixels_used=best.pixels,
        open_water_pixels=0,
        range_span_m=None,
        bootstrap=reps,
        seed=seed,
    )


def _nearest_jerlov(beta: Coefficient, *, ratios: bool) -> str | None:
    """The Jerlov type nearest in log beta (or log ratio to green) over the identified channels, or None."""
    idx = [c for c in range(3) if beta.identified[c] and beta.value[c] and beta.value[c] > 0]
    if ratios:
        idx = [c for c in idx if c != 1]
    if not idx:
        return None
    got = np.log([beta.value[c] for c in idx])
    best, best_d = None, np.inf
    for name in JERLOV_TYPES:
        ref = jerlov_beta(name)
        ref = ref / ref[1] if ratios else ref
        d = float(np.sum((np.log(ref[idx]) - got) ** 2))
        if d < best_d:
            best, best_d = name, d
    return best
