"""Procedural texture sets (seasynth.worker.scene.assets.textures): deterministic bytes, seamless tiling, an albedo
factor of mean 1, and normal maps that are the unit normals of the stored relief in the glTF convention."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.worker.frame.srgb import SRGB8_TO_LINEAR
from seasynth.worker.scene.assets.textures import FAMILIES, TILE_M, TextureSet, _texture_set, normal_map, texture_set

families = st.sampled_from(FAMILIES)
variants = st.integers(0, 2**31)
sizes = st.sampled_from([16, 32, 64])
SMALL = settings(max_examples=30, deadline=None)


def digest(t: TextureSet) -> str:
    return hashlib.sha256(t.albedo.tobytes() + t.normal.tobytes() + t.height_m.tobytes()).hexdigest()


def factor(t: TextureSet) -> np.ndarray:
    """The linear albedo factor (n, n, 3) float64 the renderer multiplies a surface's albedo by."""
    return t.albedo_gain * SRGB8_TO_LINEAR[t.albedo]


def decoded_normals(t: TextureSet) -> np.ndarray:
    return t.normal.astype(np.float64) / 255.0 * 2.0 - 1.0


@SMALL
@given(families, variants, sizes)
def test_shapes_dtypes_key_and_source(family, variant, size):
    t = texture_set(family, variant, size)
    assert t.albedo.shape == t.normal.shape == (size, size, 3)
    assert t.albedo.dtype == t.normal.dtype == np.uint8
    assert t.height_m.shape == (size, size) and t.height_m.dtype == np.float32
    assert t.key == f"texture/{family}/{variant}/size={size}"
    assert t.source == f"procedural:{family}#{variant}"
    assert t.tile_m == TILE_M[family]


@SMALL
@given(families, variants, sizes)
def test_the_same_arguments_give_the_same_bytes_without_the_cache(family, variant, size):
    a, b = _texture_set.__wrapped__(family, variant, size), _texture_set.__wrapped__(family, variant, size)
    assert a is not b
    assert digest(a) == digest(b)
    assert a.albedo_gain == b.albedo_gain
    assert a == b and hash(a) == hash(b)  # equality goes by key


def test_a_fresh_process_makes_the_same_bytes():
    code = ("import hashlib; from seasynth.worker.scene.assets.textures import texture_set as f; t = f('pebbles', 7, 64); "
            "print(hashlib.sha256(t.albedo.tobytes() + t.normal.tobytes() + t.height_m.tobytes()).hexdigest(),"
            " repr(t.albedo_gain))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    t = texture_set("pebbles", 7, 64)
    assert out == [digest(t), repr(t.albedo_gain)]


def test_the_cache_hands_back_the_same_object():
    assert texture_set("coral", 2, 32) is texture_set("coral", 2, 32)


@SMALL
@given(families, variants, sizes)
def test_variants_differ(family, variant, size):
    a, b = texture_set(family, variant, size), texture_set(family, variant + 1, size)
    assert not np.array_equal(a.height_m, b.height_m)
    assert not np.array_equal(a.albedo, b.albedo)
    assert a != b


def test_families_differ():
    assert len({digest(texture_set(f, 0, 32)) for f in FAMILIES}) == len(FAMILIES)


def seam_and_interior(a: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """|difference| between neighbours across the image border along `axis`, and between interior neighbours."""
    a = np.moveaxis(np.asarray(a, np.float64), axis, 0)
    return np.abs(a[0] - a[-1]), np.abs(np.diff(a, axis=0))


def seamless(a: np.ndarray, axis: int) -> bool:
    """The seam (one of n neighbour rows) is not an outlier among the n - 1 interior ones: its largest step is
    at most 1.5 x the largest interior step and its mean step at most 1.5 x the largest interior row's mean
    (for a periodic map being the very largest has odds 1/n, so no tighter bound is stable)."""
    seam, interior = seam_and_interior(a, axis)
    rows = interior.reshape(len(interior), -1).mean(axis=1)
    return bool(seam.max() <= 1.5 * interior.max() and seam.mean() <= 1.5 * rows.max())


@SMALL
@given(families, variants, st.sampled_from([32, 64, 128]))
def test_every_map_tiles_seamlessly(family, variant, size):
    t = texture_set(family, variant, size)
    for name, a in (("height_m", t.height_m), ("albedo", t.albedo), ("normal", t.normal)):
        for axis in (0, 1):
            assert seamless(a, axis), (name, axis)


def test_a_seam_would_be_caught():
    """The check fails for smooth fields that do not wrap: a ramp, and a sand relief cut from a larger tile."""
    ramp = np.linspace(0.0, 1.0, 64)[:, None] + np.zeros((1, 64))
    assert not seamless(ramp, 0)
    cut = texture_set("sand", 0, 128).height_m[:64, :64]
    assert not (seamless(cut, 0) and seamless(cut, 1))


@SMALL
@given(families, variants, sizes)
def test_albedo_factor_has_mean_one_per_channel_and_a_realistic_range(family, variant, size):
    f = factor(texture_set(family, variant, size))
    np.testing.assert_allclose(f.mean(axis=(0, 1)), 1.0, rtol=0.01)
    assert f.max() <= 2.5 * 1.01
    assert f.min() >= 0.0


@pytest.mark.parametrize("family", FAMILIES)
def test_albedo_contrast_is_detail_not_cartoon(family):
    """At the design resolution the factor varies by about 5-30 % (std), and 98 % of it lies within 0.4-1.8."""
    f = factor(texture_set(family, 0, 256))
    assert 0.05 <= f.std() <= 0.3
    lo, hi = np.percentile(f, [1, 99])
    assert 0.4 <= lo and hi <= 1.8


@SMALL
@given(families, variants, sizes)
def test_normals_are_unit_and_point_out(family, variant, size):
    v = decoded_normals(texture_set(family, variant, size))
    np.testing.assert_allclose(np.linalg.norm(v, axis=-1), 1.0, atol=np.sqrt(3) / 255)  # 8-bit rounding
    assert (v[..., 2] > 0).all()


def expected_normals(h: np.ndarray, texel_m: float) -> np.ndarray:
    """Unit normals (-dh/dx, -dh/dy, 1) by central differences with explicit wrapped indices; x along increasing
    column, y along decreasing row (up the image). (n, n, 3) float64."""
    h = h.astype(np.float64)
    n = h.shape[0]
    i = np.arange(n)
    dhdx = (h[:, (i + 1) % n] - h[:, (i - 1) % n]) / (2 * texel_m)
    dhdy = (h[(i - 1) % n, :] - h[(i + 1) % n, :]) / (2 * texel_m)  # row i - 1 is above row i
    v = np.stack([-dhdx, -dhdy, np.ones_like(h)], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@SMALL
@given(families, variants, sizes)
def test_the_normal_map_is_the_relief_s_normals_at_the_design_size(family, variant, size):
    t = texture_set(family, variant, size)
    want = expected_normals(t.height_m, t.tile_m / size)
    assert np.abs(decoded_normals(t) - want).max() <= 1.0 / 255 + 1e-9  # rounding to the nearest code
    assert np.abs(t.height_m.mean()) <= 1e-3 * t.height_m.std()


def test_normal_map_convention_is_gltf_y_up_the_image():
    """Ground rising to the right tilts normals left (x < 0); rising up the image (towards row 0) tilts them down
    (y < 0): green < 128 where the relief climbs towards the top, as in OpenGL-convention normal maps."""
    n, texel = 16, 0.01
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64)
    right = normal_map(0.005 * cols, texel)[4:-4, 4:-4].astype(int)  # interior: the ramps do not wrap
    up = normal_map(-0.005 * rows, texel)[4:-4, 4:-4].astype(int)
    slope = 0.005 / texel
    code = round((-slope / np.sqrt(1 + slope**2) + 1) * 127.5)
    assert (right[..., 0] == code).all() and (right[..., 1] == 128).all()
    assert (up[..., 1] == code).all() and (up[..., 0] == 128).all()
    assert (right[..., 2] == up[..., 2]).all() and (up[..., 2] > 128).all()


@pytest.mark.parametrize("family", FAMILIES)
def test_relief_is_millimetres_to_centimetres(family):
    """Seabed sets (1 m) have mm-cm relief, asset sets (0.2 m) sub-mm to mm relief."""
    t = texture_set(family, 1, 256)
    assert t.tile_m == (1.0 if family in ("sand", "pebbles", "rock", "mud") else 0.2)
    span = float(np.ptp(t.height_m))
    assert (2e-3 <= span <= 5e-2) if t.tile_m == 1.0 else (2e-4 <= span <= 1e-2)


def test_arrays_are_read_only():
    t = texture_set("sand", 0, 16)
    for a in (t.albedo, t.normal, t.height_m):
        assert not a.flags.writeable
        with pytest.raises(ValueError):
            a[0, 0] = 0


@pytest.mark.parametrize("args, names", [
    (("lava", 0, 32), "family"),
    (("sand", -1, 32), "variant"),
    (("sand", 1.5, 32), "variant"),
    (("sand", True, 32), "variant"),
    (("sand", 0, 8), "size"),
    (("sand", 0, 4096), "size"),
    (("sand", 0, 48), "size"),
    (("sand", 0, 64.0), "size"),
])
def test_bad_arguments_raise_value_error_naming_them(args, names):
    texture_set("sand", 1, 32)  # cached first: a bad argument equal to a good one (True == 1) is still refused
    with pytest.raises(ValueError, match=names):
        texture_set(*args)


def test_numpy_integers_are_accepted_and_share_the_key():
    assert texture_set("mud", np.int64(4), np.int32(32)).key == "texture/mud/4/size=32"
