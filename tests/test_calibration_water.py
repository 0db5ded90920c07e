"""seasynth.service.calibration: the estimate written as a spec's water section, and photos and range maps read
from files (formats, units, refusals naming the file, decompression bombs); random small inputs never give NaN."""

from __future__ import annotations

import io

import imagecodecs
import numpy as np
import pytest
import yaml
from calibration_helpers import assert_no_nan, bomb_png, full_spec, photo
from PIL import Image

from seasynth.service.calibration.estimate import DEFAULT_BOOTSTRAP, estimate_water
from seasynth.service.calibration.io import MAX_PHOTO_PIXELS, read_photo, read_range
from seasynth.service.calibration.output import to_spec_water
from seasynth.service.errors import CalibrationError

# ------------------------------------------------------------------ the spec's water section


@pytest.mark.parametrize("spread", [0.0, 0.2])
def test_to_spec_water_with_range_is_the_estimate_within_spread_and_validates(spread):
    image, z = photo()
    e = estimate_water(image, z)
    water = to_spec_water(e, spread=spread)
    w = full_spec(yaml.safe_load(yaml.safe_dump(water))).water
    assert w.resolved_model == "paper" and w.jerlov == []
    for name, coeff in (("beta_D", e.beta_D), ("B_inf", e.B_inf)):
        interval = getattr(w, name)
        np.testing.assert_allclose(interval.min, np.array(coeff.value) * (1 - spread), atol=1e-6)
        np.testing.assert_allclose(interval.max, np.array(coeff.value) * (1 + spread), atol=1e-6)
    for c in range(3):  # beta_B: the estimate where identified, else 0.9 beta_D
        want = e.beta_B.value[c] if e.beta_B.identified[c] else 0.9 * e.beta_D.value[c]
        assert w.beta_B.min[c] == pytest.approx(want * (1 - spread), abs=1e-6)


def test_to_spec_water_without_range_takes_the_betas_of_a_jerlov_type():
    image, _ = photo()
    e = estimate_water(image, None)
    w = full_spec(to_spec_water(e, spread=0.1)).water
    assert w.beta_D is None and w.beta_B is None and len(w.jerlov) == 1
    assert w.beta_jitter == (0.9, 1.1)
    np.testing.assert_allclose(w.B_inf.min, np.array(e.B_inf.value) * 0.9, atol=1e-6)


@pytest.mark.parametrize("spread", [-0.1, 1.0, float("nan")])
def test_to_spec_water_refuses_a_spread_outside_0_1(spread):
    image, z = photo(h=60, w=80)
    with pytest.raises(CalibrationError, match="^spread:"):
        to_spec_water(estimate_water(image, z, bootstrap=2), spread=spread)


# ------------------------------------------------------------------ files


def png_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def test_range_maps_read_as_metres_in_each_format():
    z = np.array([[1.5, np.nan], [np.inf, 12.25]], np.float32)
    buf = io.BytesIO()
    np.save(buf, z)
    np.testing.assert_array_equal(read_range(buf.getvalue(), "r.npy"), z.astype(np.float64))
    tif = io.BytesIO()
    Image.fromarray(z).save(tif, format="TIFF")
    np.testing.assert_array_equal(read_range(tif.getvalue(), "r.TIFF"), z.astype(np.float64))
    mm = np.array([[1500, 0], [65535, 12250]], np.uint16)
    got = read_range(png_bytes(mm), "r.png")
    np.testing.assert_array_equal(got, [[1.5, np.nan], [65.535, 12.25]])


@pytest.mark.parametrize(
    ("data", "name", "message"),
    [
        (b"not an image", "photo.jpg", "^photo.jpg: not an image"),
        (png_bytes(np.zeros((4, 4), np.uint16)), "photo16.png", "^photo16.png: I;16 .16-bit. images are not taken"),
        # 16-bit colour opens as mode RGB: read as 8 bits it would keep only each sample's high byte
        (imagecodecs.png_encode(np.full((4, 4, 3), 511, np.uint16)), "photo48.png",
         r"^photo48.png: RGB with 16-bit samples \(RGB;16B\) is not taken"),
        (imagecodecs.tiff_encode(np.full((4, 4, 3), 511, np.uint16)), "photo16.tif",
         r"^photo16.tif: RGB with 16-bit samples \(RGB;16L\) is not taken"),
    ],
    ids=["not-an-image", "grey16", "rgb16-png", "rgb16-tiff"],
)
def test_bad_photos_are_refused_naming_the_file(data, name, message):
    with pytest.raises(CalibrationError, match=message):
        read_photo(data, name)


@pytest.mark.parametrize(
    ("data", "name", "message"),
    [
        (b"x", "depth.exr", "^depth.exr: unknown range map format '.exr'"),
        (b"x", "depth", r"^depth: unknown range map format '\(no suffix\)'"),
        (png_bytes(np.zeros((4, 4, 3), np.uint8)), "depth.png", "^depth.png: a RGB PNG cannot hold range"),
        (b"\x93NUMPY garbage", "depth.npy", "^depth.npy: not a NumPy .npy array"),
        (png_bytes(np.zeros((4, 4, 3), np.uint8)), "depth.tif", "^depth.tif: cannot read as an image|^depth.tif: a "),
    ],
    ids=["suffix", "no-suffix", "8bit-png", "bad-npy", "png-named-tif"],
)
def test_bad_range_maps_are_refused_naming_the_file(data, name, message):
    with pytest.raises(CalibrationError, match=message):
        read_range(data, name)


@pytest.mark.parametrize("side", [8193, 100_000])
def test_decompression_bombs_are_refused_before_decoding(side):
    assert side * side > MAX_PHOTO_PIXELS
    with pytest.raises(CalibrationError, match="^bomb.png: .*(over the limit|DecompressionBomb)"):
        read_photo(bomb_png(side, side), "bomb.png")


def test_default_bootstrap_is_used():
    image, z = photo(h=60, w=80)
    assert estimate_water(image, z).bootstrap == DEFAULT_BOOTSTRAP


def test_random_small_images_and_ranges_give_an_estimate_without_nan_or_a_calibration_error():
    """Odd sizes, few pixels, constant channels, ranges full of NaN, 0, inf: never another exception, never NaN."""
    rng = np.random.default_rng(11)
    outcomes = {"estimate": 0, "refused": 0}
    for trial in range(60):
        h, w = rng.integers(16, 48, 2)
        image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        if trial % 4 == 1:
            image[..., rng.integers(3)] = rng.integers(0, 256)  # one constant channel
        if trial % 4 == 2:
            image = np.repeat(rng.integers(0, 256, (h, 1, 3), dtype=np.uint8), w, axis=1)  # stripes
        z = rng.choice([np.nan, 0.0, -1.0, np.inf, 1.0, 5.0, 30.0], size=(h, w)) * rng.uniform(0.5, 2.0, (h, w))
        for range_m in (None, z):
            try:
                prior = "jerlov" if range_m is not None and trial % 2 else None
                e = estimate_water(image, range_m, seed=trial, bootstrap=3, prior=prior)
            except CalibrationError as err:
                assert str(err).split(":")[0] in ("image", "range_m"), err
                outcomes["refused"] += 1
            else:
                assert_no_nan(e)
                full_spec(to_spec_water(e))
                outcomes["estimate"] += 1
    assert outcomes["estimate"] > 0 and outcomes["refused"] > 0

