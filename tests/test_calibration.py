"""seasynth.service.calibration.estimate: known water recovered from synthetic hazed photos, what cannot be identified said so, and
degenerate inputs refused or reported, never NaN."""

from __future__ import annotations

import numpy as np
import pytest
from calibration_helpers import B_INF, BETA_B, BETA_D, assert_no_nan, photo, rel, seabed

from seasynth.service.calibration.estimate import estimate_water, half_code, srgb8_to_linear_table
from seasynth.service.calibration.output import describe
from seasynth.service.errors import CalibrationError
from seasynth.worker.frame.formation import haze
from seasynth.worker.frame.srgb import SRGB8_TO_LINEAR, encode_srgb8


def test_the_decode_table_is_the_workers_exactly():
    np.testing.assert_array_equal(srgb8_to_linear_table(), SRGB8_TO_LINEAR)


@pytest.mark.parametrize("sigma", [0.0, 0.01])
def test_with_range_recovers_the_water_within_tolerance(sigma):
    image, z = photo(sigma)
    e = estimate_water(image, z)
    assert_no_nan(e)
    assert e.with_range and e.range_span_m[0] >= 1.0 and e.range_span_m[1] <= 15.0
    assert e.open_water_pixels > 1000
    # B_inf: the open water shows it, within 0.002 (linear) in every channel.
    assert all(e.B_inf.identified) and np.abs(np.array(e.B_inf.value) - B_INF).max() <= 0.002
    # beta_D: every channel identified and within 8%.
    assert all(e.beta_D.identified) and rel(e.beta_D.value, BETA_D).max() <= 0.08
    # beta_B: green and blue within 10%; red's backscatter (B_inf 0.05) is weak: identified or not, not both wrong
    # and confident (within 3 of its sigmas when identified).
    assert e.beta_B.identified[1] and e.beta_B.identified[2]
    assert rel(e.beta_B.value[1:], BETA_B[1:]).max() <= 0.10
    if e.beta_B.identified[0]:
        assert abs(e.beta_B.value[0] - BETA_B[0]) <= 3 * e.beta_B.sigma[0]
    np.testing.assert_allclose(e.beta_D_ratio.value, np.array(e.beta_D.value) / e.beta_D.value[1])
    assert e.nearest_jerlov == "3C"
    assert e.absorption.identified == (False,) * 3 and "not separable" in e.absorption.note


@pytest.mark.parametrize("swing", [0.3, 0.6])
def test_when_j_changes_with_range_the_sigmas_cover_the_errors_and_beta_b_is_not_claimed(swing):
    """A scene that breaks the prior (J's brightness swings by +-swing along range): the fit is biased, and its
    sigma (the range jackknife's) says so: each identified beta_D is within 2 sigma of the truth, and no beta_B is
    identified (the backscatter cannot be told from the swing)."""
    J, z = seabed()
    along = np.where(np.isfinite(z), z, 15.0) / 15.0
    J = J * (1 + swing * np.sin(2 * np.pi * along))[..., None]
    e = estimate_water(encode_srgb8(haze(J, z, BETA_D, BETA_B, B_INF, np.float64)), z)
    assert_no_nan(e)
    assert any(e.beta_D.identified)
    for v, s, want in zip(e.beta_D.value, e.beta_D.sigma, BETA_D):
        if v is not None:
            assert abs(v - want) <= 2 * s
    assert e.beta_B.identified == (False,) * 3


@pytest.mark.parametrize("prior", ["none", None])
@pytest.mark.parametrize("drift", [-0.08, 0.08])
def test_when_backscatter_is_a_sliver_of_a_bright_drifting_scene_its_sigma_covers_the_error(drift, prior):
    """Bright J (up to 0.9) drifting by a few percent along range, and a red B_inf of 0.01 (backscatter about 1% of
    the signal): every identified beta is within 2 sigma of the truth. Fitted freely, red's beta_B cannot be told
    from the drift: the drift sensitivity's sigma says so (not claimed to better than 40%). Under the default prior
    (one beta_B / beta_D ratio for all channels, which this water has) green's and blue's backscatter give red's."""
    J, z = seabed()
    along = np.where(np.isfinite(z), z, 15.0) / 15.0
    J = 1.5 * J * (1 + drift * along)[..., None]
    b_inf = np.array([0.01, 0.15, 0.23])
    e = estimate_water(encode_srgb8(haze(J, z, BETA_D, BETA_B, b_inf, np.float64)), z, prior=prior)
    assert_no_nan(e)
    assert all(e.beta_D.identified)
    for got, want in ((e.beta_D, BETA_D), (e.beta_B, BETA_B)):
        for v, s, w in zip(got.value, got.sigma, want):
            if v is not None:
                assert abs(v - w) <= 2 * s, got.name
    if prior == "none":
        assert not e.beta_B.identified[0] or e.beta_B.sigma[0] >= 0.4 * e.beta_B.value[0]
    else:
        assert all(e.beta_B.identified) and rel(e.beta_B.value, BETA_B).max() < 0.05


def test_without_range_gives_b_inf_and_says_absolute_beta_is_not_identified():
    image, _ = photo()
    e = estimate_water(image, None)
    assert_no_nan(e)
    assert not e.with_range and e.range_span_m is None and e.open_water_pixels == 0
    # The open water is the flattest region: B_inf within 0.002.
    assert all(e.B_inf.identified) and np.abs(np.array(e.B_inf.value) - B_INF).max() <= 0.002
    for c in (e.beta_D, e.beta_B, e.beta_D_ratio):
        assert c.value == (None, None, None) and c.identified == (False, False, False)
    assert any("not identified without range" in n for n in e.notes)
    # beta_B ratios from dark pixels: green is 1 by definition; blue (1.1) within 25% (this texture's darkest pixels
    # are not black, which the prior assumes).
    assert e.beta_B_ratio.value[1] == 1.0
    assert e.beta_B_ratio.identified[2] and rel(e.beta_B_ratio.value[2], 1.1) <= 0.25
    assert "not identified" in describe(e)


def test_the_same_inputs_and_seed_give_the_same_estimate_and_another_seed_only_other_sigmas():
    image, z = photo()
    a, b = estimate_water(image, z, seed=3), estimate_water(image, z, seed=3)
    assert a == b
    c = estimate_water(image, z, seed=4)
    assert c.beta_D.value == a.beta_D.value and c.B_inf.value == a.B_inf.value


def test_large_photos_are_subsampled_to_the_pixel_budget():
    image, z = photo(h=240, w=320)
    e = estimate_water(image, z, max_pixels=240 * 320 // 4, bootstrap=4)
    assert e.pixels_used <= 240 * 320 // 4
    assert all(e.beta_D.identified) and rel(e.beta_D.value, BETA_D).max() <= 0.15


# ------------------------------------------------------------------ degenerate inputs


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros((8, 8, 3), np.uint8), "too small"),
        (np.zeros((64, 64), np.uint8), r"need \(h, w, 3\) uint8"),
        (np.zeros((64, 64, 3), np.float32), r"need \(h, w, 3\) uint8"),
        (np.full((64, 64, 3), 3, np.uint8), "too dark"),
        (np.full((64, 64, 3), 255, np.uint8), "below saturation"),
        (np.repeat(np.random.default_rng(1).integers(20, 200, (64, 64, 1), dtype=np.uint8), 3, axis=2),
         "no colour"),
    ],
    ids=["tiny", "grey", "float", "dark", "saturated", "colourless"],
)
def test_unusable_images_are_refused_naming_the_image(image, message):
    with pytest.raises(CalibrationError, match=message) as err:
        estimate_water(image, None)
    assert str(err.value).startswith("image:")


@pytest.mark.parametrize(
    "fill", [np.nan, 0.0, -1.0, np.inf, -np.inf], ids=["nan", "zero", "negative", "all-open-water", "minus-inf"]
)
def test_a_range_map_with_no_usable_range_is_refused_naming_range_m(fill):
    image, _ = photo()
    with pytest.raises(CalibrationError, match="^range_m: only 0 pixels"):
        estimate_water(image, np.full(image.shape[:2], fill))


@pytest.mark.parametrize(("kw", "message"), [({"bootstrap": 1}, "^bootstrap:"), ({"seed": -1}, "^seed:"),
                                             ({"max_pixels": 0}, "^max_pixels:"), ({"prior": "ocean"}, "^prior:")])
def test_bad_settings_are_refused_naming_them(kw, message):
    image, z = photo(h=60, w=80)
    with pytest.raises(CalibrationError, match=message):
        estimate_water(image, z, **kw)


def test_a_prior_without_range_is_refused_naming_prior():
    image, _ = photo(h=60, w=80)
    with pytest.raises(CalibrationError, match="^prior: 'jerlov' needs range_m"):
        estimate_water(image, None, prior="jerlov")


def test_the_jerlov_prior_is_the_default_recovers_a_jerlov_water_and_names_its_type():
    image, z = photo()
    e = estimate_water(image, z, prior="jerlov")
    assert_no_nan(e)
    assert all(e.beta_D.identified) and rel(e.beta_D.value, BETA_D).max() <= 0.08
    assert all(e.beta_B.identified) and rel(e.beta_B.value, BETA_B).max() <= 0.08
    assert any("prior jerlov: stage 1 chose Jerlov type 3C" in n for n in e.notes)
    assert e.as_dict() == estimate_water(image, z).as_dict()  # the default with range
    assert "prior jerlov" in e.method and "prior jerlov" not in estimate_water(image, z, prior="none").method


def test_a_water_off_the_prior_is_fitted_freely_and_says_so():
    """beta_B / beta_D of 0.5, 0.9 and 1.6 in red, green and blue: no single ratio fits, the photo rejects the
    default prior, stage 1 is the free fit (the same betas as prior none) and a note says why."""
    J, z = seabed()
    image = encode_srgb8(haze(J, z, BETA_D, BETA_D * np.array([0.5, 0.9, 1.6]), B_INF, np.float64))
    e = estimate_water(image, z)
    assert any("prior jerlov: not used: this photo rejects it" in n for n in e.notes)
    free = estimate_water(image, z, prior="none")
    assert e.beta_D.value == free.beta_D.value and e.beta_B.value == free.beta_B.value


@pytest.mark.parametrize("log_drift", [0.0, np.log(1.1), -np.log(1.1)])
def test_stage_two_fits_the_direct_signal_exactly_once_the_backscatter_is_known(log_drift):
    """Bin means of a water with a known backscatter (and J drifting with range as RangeData.with_drift states):
    stage 2, told the drift, returns beta_D on the fine grid's step, whatever stage 1's beta_D was, and leaves a
    channel with no direct signal not identified."""
    from seasynth.service.calibration.fit import BETA_GRID, FINE_POINTS, Z_NODES, RangeData, RangeFit
    from seasynth.service.calibration.refine import refine_beta_D

    nodes = np.geomspace(1.0, 20.0, Z_NODES)
    h = np.eye(Z_NODES)[::4][None].repeat(2, axis=0)  # (G=2, K=16, Z): each bin at one node
    zk = nodes[::4]
    bd, bb, binf = np.array([0.34, 0.2, 0.22]), np.array([0.3, 0.18, 0.2]), np.array([0.05, 0.15, 0.23])
    m = np.array([0.4, 0.5, 0.0])  # blue: no direct signal at all
    drift = np.exp(log_drift * np.linspace(-0.5, 0.5, Z_NODES))[::4]  # J's factor at each bin's range
    y = np.stack([np.stack([k * m[c] * drift * np.exp(-bd[c] * zk) + binf[c] * -np.expm1(-bb[c] * zk)
                            for k in (0.5, 1.5)]) for c in range(3)])
    data = RangeData(y=y, h=np.stack([h] * 3), z_nodes=nodes, open_mean=binf, open_pixels=1000,
                     finite_pixels=16000, z_lo=1.0, z_hi=20.0).with_drift(log_drift)
    first = RangeFit(bd * 0.5, bb, binf, bd * 0.1, bb * 0.1, np.ones(3, bool), np.ones(3, bool), np.ones(3, bool))
    out = refine_beta_D(data, first)
    step = (BETA_GRID[1] / BETA_GRID[0]) ** (2 / (FINE_POINTS - 1))
    assert (np.abs(np.log(out.beta_D[:2] / bd[:2])) <= np.log(step)).all()
    assert out.beta_D_inside.tolist() == [True, True, False] and out.beta_D[2] == first.beta_D[2]
    assert (out.beta_B == bb).all() and (out.B_inf == binf).all()


def test_range_of_the_wrong_shape_is_refused():
    image, z = photo()
    with pytest.raises(CalibrationError, match=r"^range_m: shape \(240, 319\) does not match"):
        estimate_water(image, z[:, :-1])


def test_nan_zero_and_negative_ranges_are_left_out_and_the_estimate_stays_finite():
    image, z = photo()
    holes = z.copy()
    holes[200:, :40] = np.nan
    holes[200:, 40:80] = 0.0
    holes[200:, 80:120] = -3.0
    e = estimate_water(image, holes)
    assert_no_nan(e)
    assert rel(e.beta_D.value, BETA_D).max() <= 0.10


def test_a_flat_image_with_range_identifies_no_beta_and_has_no_nan():
    z = seabed()[1]
    z[np.isinf(z)] = 20.0  # no open water either
    e = estimate_water(np.full((240, 320, 3), (110, 120, 130), np.uint8), z)
    assert_no_nan(e)
    assert e.beta_D.identified == (False,) * 3 and e.beta_B.identified == (False,) * 3
    assert e.B_inf.identified == (False,) * 3
    assert len([n for n in e.notes if "not identified" in n]) == 9


def test_an_image_with_no_flat_water_says_b_inf_is_a_guess():
    rng = np.random.default_rng(1)
    image = rng.integers(30, 220, (120, 160, 3), dtype=np.uint8)
    e = estimate_water(image, None)
    assert_no_nan(e)
    assert e.B_inf.identified == (False,) * 3 and any("no flat open-water region" in n for n in e.notes)


def test_half_code_is_half_an_8bit_step_in_linear_light():
    v = SRGB8_TO_LINEAR[[10, 128, 250]]
    got = half_code(v)
    step = SRGB8_TO_LINEAR[[11, 129, 251]] - v
    assert np.all(got > 0.45 * step) and np.all(got < 0.55 * step)
