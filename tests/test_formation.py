"""Tests for seasynth.worker.frame.formation and seasynth.worker.frame.srgb: haze hard cases, float32 vs float64, exact 8-bit sRGB."""

import subprocess
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from seasynth.worker.frame.formation import GLSL_HAZE, box_downsample, haze, haze_samples, transmission
from seasynth.worker.frame.srgb import SRGB8_TO_LINEAR, decode_srgb8, encode_srgb8, linear_to_srgb, srgb_to_linear

DTYPES = [np.float32, np.float64]
FAST = settings(max_examples=60, deadline=None)


@pytest.fixture(autouse=True)
def strict_floats():
    """Every test runs with floating point errors raised and warnings as errors."""
    with np.errstate(all="raise"), warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


# --- strategies -------------------------------------------------------------------------------

SHAPES = st.tuples(st.integers(1, 5), st.integers(1, 5))


def f32(v):
    """v rounded to float32, as hypothesis wants float32 bounds given exactly."""
    return float(np.float32(v))


def unit(width=32):
    return st.floats(0.0, 1.0, width=width)


def images(shape):
    """(h, w, 3) float32 linear values in [0, 1] (exactly representable in float32)."""
    return hnp.arrays(np.float32, (*shape, 3), elements=unit())


def ranges(shape, with_inf=True):
    """(h, w) float32 metres: 0, ordinary ranges, huge ones and (optionally) +inf."""
    finite = st.one_of(st.just(0.0), st.floats(0.0, 1e3, width=32), st.floats(0.0, f32(3e38), width=32))
    elements = st.one_of(finite, st.just(np.inf)) if with_inf else finite
    return hnp.arrays(np.float32, shape, elements=elements)


betas = hnp.arrays(np.float32, 3, elements=st.one_of(st.just(0.0), st.floats(f32(1e-6), 10.0, width=32)))
positive_betas = hnp.arrays(np.float32, 3, elements=st.floats(f32(1e-6), 10.0, width=32))
colours = hnp.arrays(np.float32, 3, elements=unit())


def image_and_range(with_inf=True):
    return SHAPES.flatmap(lambda s: st.tuples(images(s), ranges(s, with_inf)))


# --- haze hard cases --------------------------------------------------------------------------


@FAST
@given(data=image_and_range(), b_inf=colours, dtype=st.sampled_from(DTYPES))
def test_zero_beta_returns_the_clean_image_bitwise(data, b_inf, dtype):
    J, z = data
    out = haze(J, z, np.zeros(3), np.zeros(3), b_inf, dtype)
    assert out.dtype == dtype
    assert np.array_equal(out, J.astype(dtype)) and not np.signbit(out).any()


@FAST
@given(data=image_and_range(), beta_D=betas, beta_B=betas, b_inf=colours, dtype=st.sampled_from(DTYPES))
def test_zero_range_returns_the_clean_image_bitwise(data, beta_D, beta_B, b_inf, dtype):
    J, _ = data
    out = haze(J, np.zeros(J.shape[:2], np.float32), beta_D, beta_B, b_inf, dtype)
    assert np.array_equal(out, J.astype(dtype))


@FAST
@given(data=image_and_range(), beta_D=positive_betas, beta_B=positive_betas, b_inf=colours,
       dtype=st.sampled_from(DTYPES))
def test_open_water_returns_the_veiling_light_exactly(data, beta_D, beta_B, b_inf, dtype):
    J, _ = data
    out = haze(J, np.full(J.shape[:2], np.inf), beta_D, beta_B, b_inf, dtype)
    assert np.array_equal(out, np.broadcast_to(b_inf.astype(dtype), J.shape))


@FAST
@given(data=image_and_range(), beta_D=betas, beta_B=betas, b_inf=colours, dtype=st.sampled_from(DTYPES))
def test_haze_is_finite_and_bounded_for_any_range(data, beta_D, beta_B, b_inf, dtype):
    J, z = data
    out = haze(J, z, beta_D, beta_B, b_inf, dtype)
    assert out.shape == J.shape and np.all(np.isfinite(out))
    # Each term is a non-negative weight (<= 1) times a value in [0, 1].
    assert np.all(out >= 0) and np.all(out <= 2)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("x", [87.0, 100.0, 700.0, 708.0, 1e3, 1e6, 1e30])
def test_huge_optical_depth_flushes_to_zero_without_warnings(dtype, x):
    z = np.array([[x, x / 2, 1e-3 * x]])
    beta = np.array([1.0, 2.0, 1e3])
    t = transmission(beta, z, dtype)
    assert t.dtype == dtype and np.all(np.isfinite(t))
    x_all = beta * z[..., None]
    cutoff = 87.0 if dtype == np.float32 else 708.0
    flushed = x_all >= cutoff
    assert np.all(t[flushed] == 0)
    expected = np.exp(-x_all[~flushed])
    with np.errstate(under="ignore"):  # assert_allclose's own rtol * 1e-304
        np.testing.assert_allclose(t[~flushed], expected, rtol=1e-5 if dtype == np.float32 else 1e-13)
    J = np.full((1, 3, 3), 0.5)
    out = haze(J, z, beta, beta, np.array([0.1, 0.2, 0.3]), dtype)
    assert np.all(np.isfinite(out))
    np.testing.assert_array_equal(out[flushed], np.broadcast_to([0.1, 0.2, 0.3], out.shape)[flushed].astype(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_transmission_hard_cases(dtype):
    z = np.array([[0.0, 1.0, 10.0, np.inf]])
    t = transmission(np.array([0.0, 0.1, 1e6]), z, dtype)
    assert np.array_equal(t[..., 0], np.ones((1, 4)))  # beta = 0: 1 even at +inf (no 0 * inf)
    assert t[0, 3, 1] == 0 and t[0, 3, 2] == 0  # +inf: exactly 0
    assert np.all(t[0, 0] == 1)  # z = 0: exactly 1
    assert t[0, 1, 1] == pytest.approx(np.exp(-0.1), rel=1e-7)
    assert t[0, 2, 2] == 0


@FAST
@given(
    z=hnp.arrays(np.float32, (4, 4), elements=st.floats(f32(1e-3), 1e3, width=32)),
    beta_B=hnp.arrays(np.float32, 3, elements=st.floats(f32(1e-9), f32(1e-5), width=32)),
    dtype=st.sampled_from(DTYPES),
)
def test_small_backscatter_matches_expm1(z, beta_B, dtype):
    # x = beta_B * z in [1e-12, 1e-2]: 1 - exp(-x) would lose up to all digits; expm1 keeps them.
    out = haze(np.zeros((4, 4, 3)), z, np.zeros(3), beta_B, np.ones(3), dtype)
    expected = -np.expm1(-(z.astype(np.float64)[..., None] * beta_B.astype(np.float64)))
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=0)


# float32 vs float64 bound, for J, B_inf in [0, 1] given exactly in float32: each output is
# J * t + B * a.  The optical depth x is rounded once (relative 2^-24), moving t by at most
# t * x * 2^-24 <= 2^-24 / e, and a likewise; numpy's float32 exp and the tanh form of 1 - exp(-x)
# are within ~2e-7 relative (measured: 1.9e-7 and 2.0e-7); the products and the sum add three
# roundings of <= 2^-24 * 2.  Total < 1e-6; we assert 2e-6 to leave room for other libm builds.
F32_F64_ATOL = 2e-6


@FAST
@given(data=image_and_range(), beta_D=betas, beta_B=betas, b_inf=colours)
def test_float32_and_float64_agree(data, beta_D, beta_B, b_inf):
    J, z = data
    fast = haze(J, z, beta_D, beta_B, b_inf, np.float32)
    ref = haze(J, z, beta_D, beta_B, b_inf, np.float64)
    np.testing.assert_allclose(fast, ref, rtol=0, atol=F32_F64_ATOL)


def test_float32_and_float64_agree_on_a_dense_sweep():
    x = np.geomspace(1e-8, 200.0, 200_000, dtype=np.float32).reshape(400, 500)
    J = np.linspace(0, 1, x.size * 3, dtype=np.float32).reshape(400, 500, 3)
    args = (np.array([1.0, 0.3, 0.01]), np.array([1.0, 0.5, 0.02]), np.array([0.2, 0.6, 1.0]))
    diff = np.abs(haze(J, x, *args, np.float32) - haze(J, x, *args, np.float64))
    assert diff.max() <= F32_F64_ATOL


def test_haze_matches_the_model_in_float64():
    rng = np.random.default_rng(7)
    J = rng.random((6, 7, 3))
    z = rng.uniform(0, 40, (6, 7))
    beta_D, beta_B, b_inf = np.array([0.4, 0.1, 0.05]), np.array([0.3, 0.12, 0.08]), np.array([0.01, 0.15, 0.23])
    expected = J * np.exp(-beta_D * z[..., None]) + b_inf * (1 - np.exp(-beta_B * z[..., None]))
    np.testing.assert_allclose(haze(J, z, beta_D, beta_B, b_inf, np.float64), expected, rtol=1e-14, atol=1e-15)


def test_haze_leaves_its_inputs_alone():
    J = np.full((2, 2, 3), 0.5, np.float32)
    z = np.array([[1.0, np.inf], [0.0, 3.0]], np.float32)
    J0, z0 = J.copy(), z.copy()
    haze(J, z, np.full(3, 0.1), np.full(3, 0.1), np.full(3, 0.2))
    assert np.array_equal(J, J0) and np.array_equal(z, z0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"range_m": np.array([[-1.0, 1.0]])}, "range_m"),
        ({"range_m": np.array([[np.nan, 1.0]])}, "range_m"),
        ({"beta_D": np.array([-0.1, 0.1, 0.1])}, "beta_D"),
        ({"beta_B": np.array([np.inf, 0.1, 0.1])}, "beta_B"),
        ({"beta_D": np.array([0.1, 0.1])}, "beta_D"),
        ({"B_inf": np.array([np.nan, 0.1, 0.1])}, "B_inf"),
        ({"J": np.zeros((1, 3, 3))}, "J"),
        ({"dtype": np.float16}, "dtype"),
    ],
)
def test_haze_rejects_bad_input_naming_it(kwargs, match):
    args = {
        "J": np.zeros((1, 2, 3)),
        "range_m": np.ones((1, 2)),
        "beta_D": np.full(3, 0.1),
        "beta_B": np.full(3, 0.1),
        "B_inf": np.full(3, 0.1),
    } | kwargs
    with pytest.raises(ValueError, match=match):
        haze(**args)


# --- supersampling ----------------------------------------------------------------------------


def test_box_downsample_averages_blocks():
    x = np.arange(4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3)
    out = box_downsample(x, 2)
    assert out.shape == (2, 3, 3) and out.dtype == np.float32
    assert np.array_equal(out, x.reshape(2, 2, 3, 2, 3).mean(axis=(1, 3)))
    assert np.array_equal(box_downsample(x[..., 0], 2, accumulate=np.float64), out[..., 0])
    assert np.array_equal(box_downsample(x, 1), x)


@pytest.mark.parametrize("s", [0, 3, 2.0])
def test_box_downsample_rejects_bad_factors(s):
    with pytest.raises(ValueError, match="s"):
        box_downsample(np.zeros((4, 4, 3)), s)


def test_haze_samples_hazes_each_sample_before_averaging():
    # A thin spine at 1 m against open water: the resolved pixel is the mean of hazed samples.
    J = np.zeros((2, 2, 3), np.float32)
    J[0, 0] = 1.0
    z = np.full((2, 2), np.inf, np.float32)
    z[0, 0] = 1.0
    beta, b_inf = np.full(3, 0.5), np.array([0.0, 0.1, 0.2])
    out = haze_samples(J, z, beta, beta, b_inf, 2, np.float64)
    spine = np.exp(-0.5) + b_inf * (1 - np.exp(-0.5))
    np.testing.assert_allclose(out[0, 0], (spine + 3 * b_inf) / 4, rtol=1e-15)
    assert np.array_equal(haze_samples(J, z, beta, beta, b_inf, 1), haze(J, z, beta, beta, b_inf))


# --- sRGB -------------------------------------------------------------------------------------


def test_decode_table_is_the_iec_formula():
    c = np.arange(256) / 255.0
    expected = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    assert SRGB8_TO_LINEAR.shape == (256,) and SRGB8_TO_LINEAR.dtype == np.float64
    assert np.array_equal(SRGB8_TO_LINEAR, expected)
    assert SRGB8_TO_LINEAR[0] == 0 and SRGB8_TO_LINEAR[255] == 1
    assert not SRGB8_TO_LINEAR.flags.writeable


@pytest.mark.parametrize("dtype", DTYPES)
def test_all_256_codes_round_trip(dtype):
    codes = np.arange(256, dtype=np.uint8)
    linear = decode_srgb8(codes, dtype)
    assert linear.dtype == dtype
    assert np.array_equal(encode_srgb8(linear), codes)
    s = linear_to_srgb(linear)
    np.testing.assert_allclose(s * 255, np.arange(256), atol=1e-3 if dtype == np.float32 else 1e-9)


def test_transfer_functions_are_inverse():
    s = np.linspace(0, 1, 10_001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(s)), s, rtol=0, atol=1e-12)
    assert srgb_to_linear(np.float32(0.5)).dtype == np.float32
    assert linear_to_srgb(np.array([0.0, 1.0])).tolist() == pytest.approx([0.0, 1.0], abs=1e-15)


@pytest.mark.parametrize("c", [0, 1, 10, 11, 100, 187, 254])
def test_encode_rounds_a_tie_up(c):
    # The linear value whose sRGB value is exactly halfway between codes c and c + 1.
    tie = srgb_to_linear(np.float64((c + 0.5) / 255))
    assert encode_srgb8(np.array([tie]))[0] == c + 1
    assert encode_srgb8(np.array([np.nextafter(tie, 0.0)]))[0] == c
    # float32: the first float32 at or above the tie goes up, the one below stays.
    up = np.float32(tie)
    if up < tie:
        up = np.nextafter(up, np.float32(1))
    assert encode_srgb8(np.array([up]))[0] == c + 1
    assert encode_srgb8(np.array([np.nextafter(up, np.float32(0))]))[0] == c


@settings(max_examples=100, deadline=None)
@given(x=hnp.arrays(np.float32, 64, elements=st.floats(-0.5, 1.5, width=32)), dtype=st.sampled_from(DTYPES))
def test_encode_is_round_half_up_of_the_transfer(x, dtype):
    s = 255 * linear_to_srgb(np.clip(x.astype(np.float64), 0, 1))
    clear_of_ties = np.abs(s - np.floor(s) - 0.5) > 1e-9  # the float64 formula itself is fuzzy at ties
    expected = np.floor(s + 0.5).astype(np.uint8)
    assert np.array_equal(encode_srgb8(x.astype(dtype))[clear_of_ties], expected[clear_of_ties])


def test_encode_dense_float32_matches_the_float64_thresholds():
    x = np.linspace(-0.01, 1.01, 1_000_003, dtype=np.float32)
    thresholds = srgb_to_linear((np.arange(255) + 0.5) / 255)
    expected = np.searchsorted(thresholds, np.clip(x.astype(np.float64), 0, 1), side="right")
    assert np.array_equal(encode_srgb8(x), expected)


@pytest.mark.parametrize("dtype", DTYPES)
def test_encode_clips_and_keeps_shape(dtype):
    x = np.array([[-np.inf, -1.0, -0.0, 0.0, 1.0, 1.5, np.inf, 0.5]], dtype)
    assert encode_srgb8(x).tolist() == [[0, 0, 0, 0, 255, 255, 255, 188]]
    img = np.random.default_rng(1).random((5, 7, 3)).astype(dtype)
    out = encode_srgb8(img[:, ::2])  # non-contiguous input
    assert out.shape == (5, 4, 3) and out.dtype == np.uint8
    assert np.array_equal(out, encode_srgb8(np.ascontiguousarray(img[:, ::2])))


def test_encode_rejects_nan():
    with pytest.raises(ValueError, match="NaN"):
        encode_srgb8(np.array([0.5, np.nan], np.float32))


def test_decode_requires_uint8():
    with pytest.raises(TypeError, match="uint8"):
        decode_srgb8(np.array([1, 2]))


# --- GLSL -------------------------------------------------------------------------------------


def test_glsl_defines_haze_with_the_hard_cases():
    assert "vec3 haze(vec3 J, float z, vec3 betaD, vec3 betaB, vec3 Binf)" in GLSL_HAZE
    assert "isinf(z)" in GLSL_HAZE and "beta <= 0.0" in GLSL_HAZE
    assert GLSL_HAZE.count("{") == GLSL_HAZE.count("}")
    assert "#version" not in GLSL_HAZE  # included into a shader that declares its own


def test_glsl_compiles_as_a_330_fragment_shader(tmp_path):
    shader = tmp_path / "haze.frag"
    shader.write_text(
        "#version 330 core\n" + GLSL_HAZE + "uniform vec3 betaD; uniform vec3 betaB; uniform vec3 Binf;\n"
        "in vec3 J; in float z; out vec4 color;\n"
        "void main() { color = vec4(haze(J, z, betaD, betaB, Binf), 1.0); }\n"
    )
    result = subprocess.run(["glslangValidator", str(shader)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout


def _glsl_haze_in_numpy(J, z, beta_D, beta_B, b_inf):
    """The GLSL branches, transliterated in float32 (what a driver computes, up to its exp)."""
    f = np.float32
    J, z = J.astype(f), z.astype(f)[..., None]

    def depth(beta):
        beta = beta.astype(f)
        return np.where(beta <= 0, f(0), np.where(np.isinf(z), f(87), np.minimum(beta * z, f(87)))).astype(f)

    with np.errstate(all="ignore"):  # GPUs do not trap; np.where evaluates both branches
        xd, xb = depth(beta_D), depth(beta_B)
        t = np.where(xd >= 87, f(0), np.exp(-xd))
        c = [f(1 / k) for k in (2, 6, 24, 120, 720, 5040)]
        series = xb * (1 - xb * (c[0] - xb * (c[1] - xb * (c[2] - xb * (c[3] - xb * (c[4] - xb * c[5]))))))
        a = np.where(xb < 0.125, series, np.where(xb >= 87, f(1), 1 - np.exp(-xb)))
        return (J * t + b_inf.astype(f) * a).astype(f)


@FAST
@given(data=image_and_range(), beta_D=betas, beta_B=betas, b_inf=colours)
def test_glsl_algorithm_agrees_with_numpy_within_one_code(data, beta_D, beta_B, b_inf):
    J, z = data
    glsl = encode_srgb8(_glsl_haze_in_numpy(J, z, beta_D, beta_B, b_inf)).astype(int)
    ours = encode_srgb8(haze(J, z, beta_D, beta_B, b_inf)).astype(int)
    assert np.abs(glsl - ours).max() <= 1
