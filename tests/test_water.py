"""Tests for seasynth.service.water: the Jerlov table, its betas and default veiling light."""

import numpy as np
import pytest

from seasynth.service.water import (
    JERLOV_TRANSMITTANCE,
    JERLOV_TYPES,
    JERLOV_VEILING_LIGHT,
    jerlov_beta,
    jerlov_transmittance,
    jerlov_veiling_light,
)

# Approximate betas (1/m, R, G, B) from the reference table; 1C is ours (between III and 3C).
REFERENCE_BETA = {
    "I": (0.10, 0.04, 0.018),
    "II": (0.22, 0.08, 0.06),
    "III": (0.29, 0.12, 0.12),
    "1C": (0.31, 0.15, 0.16),
    "3C": (0.34, 0.20, 0.22),
    "5C": (0.40, 0.32, 0.40),
    "7C": (0.48, 0.49, 0.53),
    "9C": (0.60, 0.78, 1.24),
}
OCEANIC = ("I", "II", "III")
COASTAL = ("1C", "3C", "5C", "7C", "9C")


def test_types_are_the_table_keys_in_order():
    assert JERLOV_TYPES == ("I", "II", "III", "1C", "3C", "5C", "7C", "9C")
    assert tuple(JERLOV_TRANSMITTANCE) == JERLOV_TYPES
    assert tuple(JERLOV_VEILING_LIGHT) == JERLOV_TYPES


@pytest.mark.parametrize("name", JERLOV_TYPES)
def test_beta_is_minus_log_of_the_stored_transmittance(name):
    n = jerlov_transmittance(name)
    beta = jerlov_beta(name)
    assert n.shape == beta.shape == (3,) and beta.dtype == np.float64
    assert np.array_equal(beta, -np.log(np.array(JERLOV_TRANSMITTANCE[name])))
    assert np.all((n > 0) & (n < 1))


@pytest.mark.parametrize("name", JERLOV_TYPES)
def test_beta_reproduces_the_reference_table(name):
    np.testing.assert_allclose(jerlov_beta(name), REFERENCE_BETA[name], rtol=0, atol=1e-4)


def test_transmittance_used_as_beta_would_reverse_the_order():
    # Guards the classic slip: N is near 1 for clear water, beta near 0.
    assert np.all(jerlov_beta("I") < jerlov_transmittance("I"))


def test_clear_oceanic_water_has_the_smallest_betas():
    clear = jerlov_beta("I")
    for name in JERLOV_TYPES[1:]:
        assert np.all(clear < jerlov_beta(name)), name


@pytest.mark.parametrize("name", OCEANIC)
def test_red_attenuates_most_in_oceanic_water(name):
    r, g, b = jerlov_beta(name)
    assert r > g and r > b


@pytest.mark.parametrize("series", [OCEANIC, COASTAL])
def test_betas_increase_with_type_in_every_channel(series):
    betas = np.stack([jerlov_beta(name) for name in series])
    assert np.all(np.diff(betas, axis=0) > 0)


@pytest.mark.parametrize("name", JERLOV_TYPES)
def test_veiling_light_is_linear_rgb(name):
    b_inf = jerlov_veiling_light(name)
    assert b_inf.shape == (3,) and b_inf.dtype == np.float64
    assert np.all((b_inf >= 0) & (b_inf <= 1))


def test_veiling_light_is_blue_offshore_and_greener_inshore():
    for name in OCEANIC:
        r, g, b = jerlov_veiling_light(name)
        assert b > g > r, name
    # Oceanic blue gets darker as water gets murkier; the reference green coastal colour is 3C's.
    blues = [jerlov_veiling_light(name)[2] for name in OCEANIC]
    assert blues == sorted(blues, reverse=True)
    np.testing.assert_array_equal(jerlov_veiling_light("3C"), (0.007, 0.147, 0.233))
    green_share = [jerlov_veiling_light(n)[1] / jerlov_veiling_light(n).sum() for n in ("III", "1C", "3C", "5C", "7C", "9C")]
    assert green_share == sorted(green_share)


def test_returned_arrays_are_copies():
    jerlov_beta("I")[0] = 99.0
    jerlov_veiling_light("I")[0] = 99.0
    jerlov_transmittance("I")[0] = 99.0
    assert jerlov_beta("I")[0] == pytest.approx(0.10, abs=1e-4)
    assert jerlov_veiling_light("I")[0] < 1


@pytest.mark.parametrize("bad", ["IV", "i", "3c", "", None, 3])
@pytest.mark.parametrize("fn", [jerlov_beta, jerlov_transmittance, jerlov_veiling_light])
def test_unknown_type_names_it_and_the_known_types(fn, bad):
    with pytest.raises(ValueError) as info:
        fn(bad)
    message = str(info.value)
    assert repr(bad) in message
    assert all(name in message for name in JERLOV_TYPES)


def test_the_recorded_jerlov_type_is_the_one_the_water_used():
    from seasynth.service.seeds import frame_rng
    from seasynth.service.spec.dataset import parse_spec
    from seasynth.worker.scene.sample import _sample_water

    rgb = {"min": [0.1, 0.05, 0.02], "max": [0.2, 0.1, 0.05]}
    explicit = parse_spec({"water": {"jerlov": ["7C"], "beta_D": rgb, "B_inf": rgb}})
    from_type = parse_spec({"water": {"jerlov": ["7C"], "beta_D": rgb}})  # B_inf comes from 7C's veiling light
    for i in range(5):
        water, kind = _sample_water(explicit, frame_rng(1, i))
        assert kind is None and np.all((water.beta_D >= rgb["min"]) & (water.beta_D <= rgb["max"]))
        water, kind = _sample_water(from_type, frame_rng(1, i))
        assert kind == "7C"
