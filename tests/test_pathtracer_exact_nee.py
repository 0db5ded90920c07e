"""Exact shadow-ray transmittance (bench/pathtracer_integrator.py): the same expectation as Mitsuba's volpath, and
less noise where the sun is seen through absorbing water."""

import dataclasses
import hashlib
import importlib.util
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

if importlib.util.find_spec("mitsuba") is None:
    pytest.skip("mitsuba is not installed (pip install -e '.[bench]')", allow_module_level=True)

from seasynth.bench import pathtracer as pt
from seasynth.bench.transfer_noise import BLOCK, block_means
from seasynth.bench.transfer_recipe import REPO, held_out_specs, load_recipe
from tests.test_pathtracer_export import flat_scene, view_distance

TINY = REPO / "bench" / "recipes" / "transfer-tiny.json"


@pytest.fixture(scope="module", autouse=True)
def _libllvm():
    pt.use_libllvm()


@settings(max_examples=4, deadline=None)
@given(a=st.tuples(*[st.floats(0.1, 0.3)] * 3), depth=st.floats(4.0, 10.0))
def test_in_absorbing_water_both_estimators_are_exact_on_average_and_the_exact_one_has_under_0_7_the_error(a, depth):
    """A white plane under the sun in purely absorbing water: each estimator's mean ratio to the closed form
    E cos/pi exp(-a (d + depth / cos)) is 1 within 5 standard errors; exact transmittance's standard error is
    under 0.7 of tracking's (its shadow rays no longer return 0 or 1 / exp(-a depth / cos))."""
    E, a = np.array([1.0, 2.0, 3.0]), np.array(a)
    scene = flat_scene(sigma_a=a, sun=E, surface_z=depth)
    d, _ = view_distance(scene)
    cos_sun = np.cos(np.radians(30.0))
    expected = E * cos_sun / np.pi * np.exp(-a * (d + depth / cos_sun))
    se = {}
    for exact in (False, True):
        ratio = (pt.render(scene, spp=32, seed=5, exact_nee=exact) / expected).reshape(-1, 3)
        se[exact] = ratio.std(axis=0, ddof=1) / np.sqrt(len(ratio))
        np.testing.assert_array_less(np.abs(ratio.mean(axis=0) - 1.0), 5.0 * se[exact])
    np.testing.assert_array_less(se[True], 0.7 * se[False])


def tiny_scene(group: int, frame: int, width: int):
    from seasynth.bench.fidelity_scene import exported_scene
    from seasynth.bench.transfer_testset import held_out_scene
    from seasynth.worker.frame.function import RenderSession

    recipe = load_recipe(TINY)
    recipe = recipe.model_copy(update={"width": width, "height": width * recipe.height // recipe.width})
    _, spec = held_out_specs(recipe)[group]
    with RenderSession() as s:
        return exported_scene(s, spec, held_out_scene(s, spec, frame))


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=st.sampled_from([(0, 0), (0, 1), (1, 0)]), drop_sky=st.booleans())
def test_on_held_out_scenes_the_exact_estimator_s_block_means_agree_with_volpath_s_within_their_noise(case, drop_sky):
    """Scattering water, sun, sky and lamps (the tiny recipe's scenes, 48x36): per channel, the 8x8 block means of
    the two estimators differ by an RMS at most 2.5 times what their noise gives (each image is the mean of two
    halves; its error's variance is a quarter of the halves' squared difference), and the image means by at most
    4 standard errors of that noise. A changed expectation (a camera ray not attenuated by the water it starts in;
    a shadow ray that skips the water) is many times larger than this noise."""
    scene = tiny_scene(*case, width=48)
    if drop_sky:
        scene = dataclasses.replace(scene, sky_radiance_rgb=np.zeros(3))
    halves = {exact: pt.render_seeds(scene, 16, (0, 1), max_depth=16, lamp_housing_m=0.05, exact_nee=exact)
              for exact in (False, True)}
    means = {k: block_means((h[0] + h[1]) / 2) for k, h in halves.items()}
    var = sum((block_means(h[0]) - block_means(h[1])) ** 2 / 4 for h in halves.values())  # (bh, bw, 3)
    diff = means[True] - means[False]
    assert diff.shape[:2] == (36 // BLOCK, 48 // BLOCK)
    np.testing.assert_array_less(np.sqrt((diff ** 2).mean(axis=(0, 1))), 2.5 * np.sqrt(var.mean(axis=(0, 1))))
    np.testing.assert_array_less(np.abs(diff.mean(axis=(0, 1))), 4.0 * np.sqrt(var.sum(axis=(0, 1))) / var[..., 0].size)


def test_the_transfer_recipes_use_exact_transmittance_and_a_recipe_without_it_keeps_its_old_test_set_digest():
    from seasynth.bench.transfer_testset import testset_digest

    for name in ("transfer.json", "transfer-tiny.json"):
        recipe = load_recipe(REPO / "bench" / "recipes" / name)
        assert recipe.test.exact_nee
        off = recipe.model_copy(update={"test": recipe.test.model_copy(update={"exact_nee": False})})
        before = json.dumps([(REPO / off.base_spec).read_text(), off.width, off.height,
                             off.test.model_dump(exclude={"min_contrast", "exact_nee"})], sort_keys=True)
        assert testset_digest(off) == hashlib.sha256(before.encode()).hexdigest() != testset_digest(recipe)
