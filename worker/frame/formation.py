"""Underwater image formation (revised Akkaynak-Treibitz model) in linear light; its 8-bit sRGB is worker.srgb."""

from __future__ import annotations

import numpy as np

__all__ = [
    "GLSL_HAZE",
    "box_downsample",
    "haze",
    "haze_samples",
    "transmission",
]

# ---------------------------------------------------------------------------------------------
# Attenuation and haze
# ---------------------------------------------------------------------------------------------

# Optical depths x = beta * z beyond which exp(-x) is flushed to 0: exp(-x) stays a normal number
# below them (float32 normals end near exp(-87.3), float64 near exp(-708.4)), so no underflow
# warning and no denormal slow path.
_X_MAX: dict[np.dtype, float] = {np.dtype(np.float32): 87.0, np.dtype(np.float64): 708.0}

# Coefficients below this are treated as 0: their attenuation is invisible at any sane range, and
# dropping them keeps the range cap below finite.
_BETA_TINY = 1e-30


def _check_dtype(dtype: type) -> np.dtype:
    dt = np.dtype(dtype)
    if dt not in _X_MAX:
        raise ValueError(f"dtype must be float32 or float64, got {dt}")
    return dt


def _check_beta(beta: np.ndarray, name: str) -> np.ndarray:
    """(3,) float64, finite, >= 0, with tiny values set to 0."""
    b = np.asarray(beta, dtype=np.float64)
    if b.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {b.shape}")
    if not (np.all(np.isfinite(b)) and np.all(b >= 0)):
        raise ValueError(f"{name} must be finite and >= 0, got {b.tolist()}")
    return np.where(b < _BETA_TINY, 0.0, b)


def _capped_range(range_m: np.ndarray, dt: np.dtype, *betas: np.ndarray) -> np.ndarray:
    """Range clipped where every positive coefficient already gives x >= 2 * x_max.

    Keeps products finite (0 * inf never happens) while +inf and huge ranges still flush.
    range_m: (h, w), metres, >= 0 or +inf.  Returns (h, w) `dt`, finite (new array).
    """
    z = np.asarray(range_m)
    if z.ndim != 2:
        raise ValueError(f"range_m must have shape (h, w), got {z.shape}")
    if z.size and not z.min() >= 0:
        raise ValueError("range_m must be >= 0 (or +inf) everywhere; found a negative or NaN range")
    positive = np.concatenate(betas)
    positive = positive[positive > 0]
    cap = 2.0 * _X_MAX[dt] / positive.min() if positive.size else 0.0
    return np.minimum(z, dt.type(cap), dtype=dt)


def _times_channels(zc: np.ndarray, v: np.ndarray, dt: np.dtype) -> np.ndarray:
    """zc[..., None] * v as (h, w, 3) `dt`.  One pass per channel: numpy's broadcast over a
    trailing axis of 3 is ~10x slower than three strided passes."""
    out = np.empty((*zc.shape, 3), dt)
    with np.errstate(under="ignore", over="ignore"):  # subnormal products act as 0, huge ones flush
        for c in range(3):
            np.multiply(zc, dt.type(v[c]), out=out[..., c])
    return out


def _scale_channels(a: np.ndarray, v: np.ndarray) -> None:
    """a[..., c] *= v[c] in place.  a: (h, w, 3); v: (3,)."""
    for c in range(3):
        a[..., c] *= a.dtype.type(v[c])


def _transmission_from(zc: np.ndarray, beta: np.ndarray, dt: np.dtype) -> np.ndarray:
    """exp(-beta * zc), flushed to 0 where beta * zc >= x_max.  zc: (h, w) finite.  -> (h, w, 3) dt."""
    x_max = dt.type(_X_MAX[dt])
    t = _times_channels(zc, -beta, dt)
    keep = t > -x_max
    np.maximum(t, -x_max, out=t)
    np.exp(t, out=t)
    np.multiply(t, keep.view(np.uint8), out=t)
    return t


def _one_minus_exp_from(zc: np.ndarray, beta: np.ndarray, dt: np.dtype) -> np.ndarray:
    """1 - exp(-beta * zc), accurate for small x; exactly 0 at x = 0, 1 at large x.  -> (h, w, 3) dt."""
    if dt == np.float64:
        a = _times_channels(zc, -beta, dt)
        np.maximum(a, -_X_MAX[dt], out=a)  # expm1(-708) is exactly -1
        np.expm1(a, out=a)
        np.negative(a, out=a)
        return a
    # float32: 1 - exp(-x) = 2h / (1 + h) = 2 / (1 + 1/h), h = tanh(x / 2), all in place.  numpy's
    # float32 expm1 is scalar libm (~9 ms per 640x480x3); tanh is vectorised and this form keeps
    # ~2e-7 relative accuracy.  h = 0 (x = 0) gives 1/h = inf and exactly 0.
    h = _times_channels(zc, 0.5 * beta, dt)
    np.tanh(h, out=h)
    with np.errstate(divide="ignore", over="ignore"):
        np.reciprocal(h, out=h)
    h += dt.type(1.0)
    np.divide(dt.type(2.0), h, out=h)
    return h


def transmission(beta: np.ndarray, range_m: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Transmission exp(-beta * z) per pixel and channel.

    beta: (3,) 1/m, finite, >= 0.  range_m: (h, w) metres, >= 0, +inf where no surface.
    Returns (h, w, 3) `dtype` (float32 or float64) in [0, 1]: exactly 1 where beta == 0 (any z,
    +inf included), exactly 0 where beta > 0 and z = +inf or beta * z >= 87 (float32) / 708 (float64).
    """
    dt = _check_dtype(dtype)
    b = _check_beta(beta, "beta")
    zc = _capped_range(range_m, dt, b)
    with np.errstate(under="ignore"):  # see haze
        return _transmission_from(zc, b, dt)


def haze(
    J: np.ndarray,
    range_m: np.ndarray,
    beta_D: np.ndarray,
    beta_B: np.ndarray,
    B_inf: np.ndarray,
    dtype: type = np.float32,
) -> np.ndarray:
    """Underwater image I = J * exp(-beta_D z) + B_inf * (1 - exp(-beta_B z)), per channel.

    J: (h, w, 3) linear radiance of the surface seen in clear water.  range_m: (h, w) metres along
    the line of sight, >= 0, +inf where no surface.  beta_D, beta_B: (3,) 1/m, finite, >= 0
    (direct attenuation, backscatter).  B_inf: (3,) linear veiling light.
    Returns (h, w, 3) `dtype` linear (new array; inputs untouched).  Exact hard cases: z = 0 or
    beta_D = beta_B = 0 -> J; z = +inf with beta_D, beta_B > 0 -> B_inf.  Finite for finite J.
    float32 is the fast path, float64 the reference; they agree within 2e-6 for J, B_inf in [0, 1].
    """
    dt = _check_dtype(dtype)
    bd = _check_beta(beta_D, "beta_D")
    bb = _check_beta(beta_B, "beta_B")
    binf = np.asarray(B_inf, dtype=np.float64)
    if binf.shape != (3,) or not np.all(np.isfinite(binf)):
        raise ValueError(f"B_inf must be (3,) and finite, got {binf.tolist()}")
    j = np.asarray(J, dtype=dt)
    if j.ndim != 3 or j.shape[2] != 3 or j.shape[:2] != np.shape(range_m):
        raise ValueError(f"J must have shape (h, w, 3) matching range_m {np.shape(range_m)}, got {j.shape}")
    zc = _capped_range(range_m, dt, bd, bb)
    # Underflow can only come from subnormal-scale inputs (ranges or betas near 1e-38): those terms
    # are as good as 0 and rounding them there is right.  Large optical depths are clipped before
    # exp, so no underflow (and no denormal slow path) arises from them.
    with np.errstate(under="ignore"):
        out = _transmission_from(zc, bd, dt)
        out *= j
        back = _one_minus_exp_from(zc, bb, dt)
        _scale_channels(back, binf)
        out += back
    return out


def box_downsample(x: np.ndarray, s: int, accumulate: type | None = None) -> np.ndarray:
    """Mean over s x s blocks (linear light in, linear light out).

    x: (h * s, w * s, ...) float.  Returns (h, w, ...) in x's dtype.  accumulate: dtype of the sum
    (e.g. np.float64 for a float32 image); None sums in x's dtype.
    """
    x = np.asarray(x)
    if not isinstance(s, (int, np.integer)) or s < 1:
        raise ValueError(f"s must be a positive integer, got {s!r}")
    if x.ndim < 2 or x.shape[0] % s or x.shape[1] % s:
        raise ValueError(f"x must have shape (h * {s}, w * {s}, ...), got {x.shape}")
    if s == 1:
        return x.copy()
    h, w = x.shape[0] // s, x.shape[1] // s
    blocks = x.reshape(h, s, w, s, *x.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=accumulate).astype(x.dtype, copy=False)


def haze_samples(
    J: np.ndarray,
    range_m: np.ndarray,
    beta_D: np.ndarray,
    beta_B: np.ndarray,
    B_inf: np.ndarray,
    s: int,
    dtype: type = np.float32,
) -> np.ndarray:
    """Haze each sample of a supersampled image, then average s x s samples in linear light.

    Hazing before resolving keeps anti-aliased edges right (a pixel mixing a near spine and open
    water cannot be hazed from its resolved colour and one range).
    J: (h * s, w * s, 3) linear.  range_m: (h * s, w * s) metres, +inf where no surface.
    Returns (h, w, 3) `dtype` linear (float64 accumulation).
    """
    return box_downsample(haze(J, range_m, beta_D, beta_B, B_inf, dtype), s, accumulate=np.float64)


GLSL_HAZE: str = """
// Underwater haze, revised Akkaynak-Treibitz model, per sample in linear light (GLSL 330):
//   I = J * exp(-betaD * z) + Binf * (1 - exp(-betaB * z))
// z: range in metres along the line of sight, +inf where no surface.  Must agree with
// seasynth.worker.frame.formation.haze (numpy float32) within 1/255 after sRGB encoding.
// Hard cases: beta == 0 -> no attenuation at any z (no 0 * inf); beta * z >= 87 or z = +inf ->
// transmission exactly 0; z == 0 -> I == J; small beta * z uses a series for 1 - exp(-x).
const float HAZE_X_MAX = 87.0;

float haze_depth(float beta, float z) {
    if (beta <= 0.0) return 0.0;
    if (isinf(z)) return HAZE_X_MAX;
    return min(beta * z, HAZE_X_MAX);
}

float haze_exp_neg(float x) {
    return x >= HAZE_X_MAX ? 0.0 : exp(-x);
}

float haze_one_minus_exp_neg(float x) {
    // Taylor series to x^7/5040 below 0.125 (truncation < x^7/40320 < 2e-11 relative), where 1 - exp(-x) in
    // float32 would lose up to 6e-8 / x relative; above, the cancellation costs less than 5e-7 relative.
    if (x < 0.125)
        return x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0 - x * (1.0 / 720.0
            - x * (1.0 / 5040.0)))))));
    return x >= HAZE_X_MAX ? 1.0 : 1.0 - exp(-x);
}

vec3 haze(vec3 J, float z, vec3 betaD, vec3 betaB, vec3 Binf) {
    vec3 I;
    for (int c = 0; c < 3; ++c) {
        float t = haze_exp_neg(haze_depth(betaD[c], z));
        float a = haze_one_minus_exp_neg(haze_depth(betaB[c], z));
        I[c] = J[c] * t + Binf[c] * a;
    }
    return I;
}
"""
"""GLSL 330 source defining `vec3 haze(vec3 J, float z, vec3 betaD, vec3 betaB, vec3 Binf)` (no #version line)."""
