"""Underwater image formation (revised Akkaynak-Treibitz model) in linear light, and exact 8-bit sRGB."""

from __future__ import annotations

import numpy as np

__all__ = [
    "GLSL_HAZE",
    "GLSL_SRGB8",
    "SRGB8_THRESHOLDS_F32",
    "SRGB8_TO_LINEAR",
    "box_downsample",
    "decode_srgb8",
    "encode_srgb8",
    "haze",
    "haze_samples",
    "linear_to_srgb",
    "srgb_to_linear",
    "transmission",
]

# ---------------------------------------------------------------------------------------------
# sRGB transfer (IEC 61966-2-1)
# ---------------------------------------------------------------------------------------------


def _float_dtype(x: np.ndarray) -> np.dtype:
    return x.dtype if x.dtype in (np.float32, np.float64) else np.dtype(np.float64)


def srgb_to_linear(x: np.ndarray | float) -> np.ndarray:
    """sRGB-encoded values -> linear light, IEC 61966-2-1 piecewise formula.

    x: any shape, sRGB in [0, 1] (values outside follow the same formulas).
    Returns the same shape; float32 for float32 input, else float64.  Computed in float64.
    """
    x = np.asarray(x)
    s = x.astype(np.float64)
    lin = np.where(s <= 0.04045, s / 12.92, ((np.maximum(s, 0.04045) + 0.055) / 1.055) ** 2.4)
    return lin.astype(_float_dtype(x), copy=False)


def linear_to_srgb(x: np.ndarray | float) -> np.ndarray:
    """Linear light -> sRGB-encoded values, IEC 61966-2-1 piecewise formula.

    x: any shape, linear in [0, 1] (values outside follow the same formulas).
    Returns the same shape; float32 for float32 input, else float64.  Computed in float64.
    """
    x = np.asarray(x)
    lin = x.astype(np.float64)
    s = np.where(lin <= 0.0031308, lin * 12.92, 1.055 * np.maximum(lin, 0.0031308) ** (1.0 / 2.4) - 0.055)
    return s.astype(_float_dtype(x), copy=False)


SRGB8_TO_LINEAR: np.ndarray = srgb_to_linear(np.arange(256) / 255.0)
"""(256,) float64: linear value of each 8-bit sRGB code (decode table)."""
SRGB8_TO_LINEAR.flags.writeable = False

# Code c + 1 starts at the linear value of the sRGB midpoint (c + 0.5) / 255; a value exactly on
# it goes up (round half up in sRGB space).  (255,) float64, strictly increasing.
_THRESHOLDS_F64: np.ndarray = srgb_to_linear((np.arange(255) + 0.5) / 255.0)


def _f64_thresholds_as(ftype: type) -> np.ndarray:
    """Thresholds in `ftype`, each the smallest `ftype` value >= the float64 one, so that for x of
    that type x >= t_ftype <=> x >= t_float64.  (255,) ftype."""
    t = _THRESHOLDS_F64.astype(ftype)
    return np.where(t < _THRESHOLDS_F64, np.nextafter(t, ftype(np.inf)), t).astype(ftype)


def _bin_tables(thresholds: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Code at each bin's start, (n,) uint8, and the first threshold above it, (n,) thresholds' dtype
    (+inf when the start is already code 255).  starts, ends: (n,) first and last value of each bin."""
    lo = np.searchsorted(thresholds, starts, side="right")
    hi = np.searchsorted(thresholds, ends, side="right")
    assert np.all(hi - lo <= 1), "encode bins must hold at most one threshold"
    padded = np.append(thresholds, np.inf).astype(thresholds.dtype)
    return lo.astype(np.uint8), padded[lo]


def _encode_tables_f32() -> tuple[np.ndarray, np.ndarray]:
    """Tables for float32, indexed by the top 16 bits of the float (sign, exponent, 7 mantissa bits).

    Non-negative floats' bits sort like the floats, and a bin spans under 1% of its value, narrower
    than the gap between thresholds, so a bin holds at most one threshold.  Negative bins (sign set)
    give 0; bins above 1.0 give 255.  Returns lo: (65536,) uint8, code at the bin start, and
    thr: (65536,) uint32, bits of the bin's threshold (0xFFFFFFFF, a NaN, where there is none).
    """
    thresholds = _f64_thresholds_as(np.float32)
    one = int(np.array(1.0, np.float32).view(np.uint32)) >> 16
    top = np.arange(one + 1, dtype=np.uint32)
    starts = (top << 16).view(np.float32)
    ends = np.minimum((top << 16) | 0xFFFF, (one << 16)).astype(np.uint32).view(np.float32)
    lo_pos, thr_pos = _bin_tables(thresholds, starts, ends)
    lo = np.zeros(1 << 16, np.uint8)
    thr = np.full(1 << 16, 0xFFFFFFFF, np.uint32)
    lo[: one + 1] = lo_pos
    lo[one + 1 : 1 << 15] = 255
    thr[: one + 1] = np.where(lo_pos < 255, thr_pos.view(np.uint32), 0xFFFFFFFF)
    return lo, thr


def _encode_tables_f64() -> tuple[np.ndarray, np.ndarray]:
    """Tables for float64 clipped to [0, 1], indexed by bits >> 45 (exponent, 7 mantissa bits).
    Returns lo: (n,) uint8 and thr: (n,) int64 threshold bits (those of +inf where none)."""
    one = int(np.array(1.0, np.float64).view(np.int64))
    starts = np.arange((one >> 45) + 1, dtype=np.int64) << 45
    ends = np.minimum(starts + ((1 << 45) - 1), one)
    lo, thr = _bin_tables(_THRESHOLDS_F64, starts.view(np.float64), ends.view(np.float64))
    return lo, thr.view(np.int64)


_LO_F32, _THR_F32 = _encode_tables_f32()
SRGB8_THRESHOLDS_F32: np.ndarray = _f64_thresholds_as(np.float32)
"""(255,) float32, ascending: a float32 linear value x has code c + 1 or more iff x >= SRGB8_THRESHOLDS_F32[c], so its
code is the number of thresholds <= x (what encode_srgb8 computes, and GLSL_SRGB8 on the GPU)."""
SRGB8_THRESHOLDS_F32.flags.writeable = False
_LO_F64, _THR_F64 = _encode_tables_f64()
_ONE_BITS_F64 = int(np.array(1.0, np.float64).view(np.int64))
_ENCODE_CHUNK = 65536  # elements per chunk in encode_srgb8


def encode_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear light -> 8-bit sRGB codes, exact, rounding half up.

    linear: (..., 3) (any shape works) float32 or float64 (other dtypes go through float64),
    linear light; clipped to [0, 1] (-0.0 and negatives -> 0, > 1 and +inf -> 255).
    Returns the same shape, uint8.  The code is round-half-up(255 * linear_to_srgb(x)) with
    the ties decided exactly: x goes to code c + 1 iff x >= srgb_to_linear((c + 0.5) / 255)
    evaluated in float64.  Raises ValueError on NaN.
    """
    x = np.asarray(linear)
    if x.dtype not in (np.float32, np.float64):
        x = x.astype(np.float64)
    if np.isnan(x).any():
        raise ValueError("encode_srgb8: linear image contains NaN")
    if x.dtype == np.float32:
        # Table lookup on the bits: no clipping pass (negatives and > 1 have their own bins).
        lo, thr, shift, itype = _LO_F32, _THR_F32, 16, np.uint32
        bits = np.ascontiguousarray(x).reshape(-1).view(itype)
    else:
        # Integer clip on the bits (sign set -> 0, above 1.0 -> 1.0), then the same lookup.
        lo, thr, shift, itype = _LO_F64, _THR_F64, 45, np.int64
        bits = np.maximum(x.reshape(-1).view(itype), 0)
        np.minimum(bits, _ONE_BITS_F64, out=bits)
    code = np.empty(bits.shape, np.uint8)
    # Cache-sized chunks with reused scratch: whole-image temporaries (a 7 MB index array) cost
    # more in page faults than the lookups themselves.
    n = min(_ENCODE_CHUNK, bits.size)
    idx, bound, up = np.empty(n, np.intp), np.empty(n, thr.dtype), np.empty(n, np.bool_)
    for start in range(0, bits.size, n):
        b = bits[start : start + n]
        k = b.size
        np.right_shift(b, shift, out=idx[:k], casting="unsafe")
        np.take(lo, idx[:k], out=code[start : start + k])
        np.take(thr, idx[:k], out=bound[:k])
        np.greater_equal(b, bound[:k], out=up[:k])
        code[start : start + k] += up[:k].view(np.uint8)  # uint8 += bool would be a slow mixed loop
    return code.reshape(x.shape)


def decode_srgb8(codes: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """8-bit sRGB codes -> linear light.

    codes: any shape, uint8.  Returns the same shape, `dtype` (float32 or float64), linear [0, 1].
    """
    codes = np.asarray(codes)
    if codes.dtype != np.uint8:
        raise TypeError(f"decode_srgb8: codes must be uint8, got {codes.dtype}")
    return SRGB8_TO_LINEAR.astype(dtype)[codes]


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
// worker.formation.haze (numpy float32) within 1/255 after sRGB encoding.
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

GLSL_SRGB8: str = """
// Exact 8-bit sRGB codes of float32 linear values: the code c with thr[c - 1] <= x < thr[c] over the 255 ascending
// float32 thresholds (SRGB8_THRESHOLDS_F32), which is encode_srgb8 of the same float32 bit for bit. The sRGB formula
// guesses c to within one code (its float32 error is ~1e-4 of a code); two comparison steps make it exact. Negatives
// and 0 give 0, values from the last threshold up (+inf too) 255. NaN compares false everywhere (code 0): srgb8()
// flags it in alpha so the reader can refuse it as encode_srgb8 does. Written as code / 255 to an 8-bit normalised
// target, which stores exactly the code (the common readback path, faster than an integer format's).
uniform float u_srgb_thr[255];
uint srgb8_code(float x) {
    if (!(x > 0.0)) return 0u;
    if (x >= u_srgb_thr[254]) return 255u;
    float s = x <= 0.0031308 ? x * 12.92 : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
    int c = clamp(int(s * 255.0 + 0.5), 0, 254);
    for (int k = 0; k < 2; ++k) {
        if (x >= u_srgb_thr[c]) c = min(c + 1, 254);
        else if (c > 0 && x < u_srgb_thr[c - 1]) c -= 1;
    }
    return uint(c);
}
vec4 srgb8(vec3 v) {
    bool nan = isnan(v.r) || isnan(v.g) || isnan(v.b);
    return vec4(uvec4(srgb8_code(v.r), srgb8_code(v.g), srgb8_code(v.b), nan ? 1u : 0u)) / 255.0;
}
"""
"""GLSL 330 source defining `vec4 srgb8(vec3 linear)`: the codes / 255 in rgb, 1 / 255 in alpha where a channel is
NaN (for an 8-bit normalised target)."""
