"""Exact 8-bit sRGB: the transfer function (IEC 61966-2-1), 8-bit codes bit-exact from float32 or float64 linear
values on the CPU (`encode_srgb8`) and on the GPU (`GLSL_SRGB8`), and their decoding."""

from __future__ import annotations

import numpy as np

__all__ = [
    "GLSL_SRGB8",
    "SRGB8_THRESHOLDS_F32",
    "SRGB8_TO_LINEAR",
    "decode_srgb8",
    "encode_srgb8",
    "linear_to_srgb",
    "srgb_to_linear",
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
