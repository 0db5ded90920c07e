"""Tests of the renderer's water from the solved water column (`seasynth.worker.light.solved`): the resolve shader
against its float64 twin, the view table against the column's own path radiance, the limit property at the beam's
c, the solve's scaling and caching, and which presets take it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_long_view import RANGES, down_or_level, radiance_along, waters
from test_render import draw
from test_render_light import CASES, CLEAR, LAMP_CASES, ONE, SCATTERING, camera, frame_and_twin, light, quad

from seasynth.worker.frame.srgb import encode_srgb8
from seasynth.worker.light import Medium
from seasynth.worker.light.build import for_spec
from seasynth.worker.light.column import path_radiance, to_sun_frame
from seasynth.worker.light.seabed import MAX_GROWTH, growth_floor
from seasynth.worker.light.sky import MU_SKY
from seasynth.worker.light.solved import (
    NODES_PHI,
    NODES_THETA,
    SolvedWater,
    ViewTable,
    irradiance,
    lookup,
    quantised,
    unit_column,
    with_column,
)
from seasynth.worker.light.unit_columns import full_column
from seasynth.worker.light.volume import volume

SOLVED = {
    "solved-sun-sky-scattering": with_column(CASES["sun-sky-scattering"]),
    "solved-optical-depth-1e6": with_column(CASES["optical-depth-1e6"]),
    "solved-lamp": with_column(LAMP_CASES["sun-sky-scattering-lamp"]),
    "solved-sky-only": with_column(light(CLEAR, SCATTERING, sun=False)),
}


@pytest.mark.parametrize("name", SOLVED)
def test_the_resolve_shader_with_the_solved_column_is_its_float64_twin_to_one_code(renderer, name):
    lt = SOLVED[name]
    assert lt.terms.solved
    image, expected, R = frame_and_twin(renderer, lt)
    got8, want8 = encode_srgb8(image).astype(int), encode_srgb8(expected).astype(int)
    assert np.isfinite(image).all() and np.abs(got8 - want8).max() <= 1
    open_water = ~np.isfinite(R)
    assert open_water.sum() > 100
    if name != "solved-optical-depth-1e6":
        assert np.all(got8[open_water, 1:] > 20)  # the solved column lights the open water


def random_table(seed: int, c: np.ndarray) -> ViewTable:
    """A view table as `_view_table` bounds it: J_ms >= 0, rates in [growth_floor c, c] (a seabed below makes J_ms
    grow with depth looking down), [-c, c] looking up; a third of the nodes at their bounds."""
    rng = np.random.default_rng(seed)
    shape = (NODES_THETA, NODES_PHI, 3)
    lo = np.broadcast_to(growth_floor()[:, None, None], shape)
    f = rng.uniform(lo, 1.0)
    f = np.where(rng.random(shape) < 1 / 6, lo, np.where(rng.random(shape) < 1 / 5, 1.0, f))
    return ViewTable(j=rng.uniform(0.0, 5.0, shape) * (rng.random(shape) < 0.9), k=f * c)


@settings(max_examples=150, deadline=None)
@given(water=waters(), data=st.data(), depth=st.floats(0.5, 200.0), sun_z=st.floats(0.05, 1.0),
       esky=st.floats(0.0, 2.0), seed=st.integers(0, 2**32 - 1))
def test_solved_a_black_surface_tends_to_open_water_at_least_as_fast_as_exp_minus_c_r(water, data, depth, sun_z,
                                                                                     esky, seed):
    """With the solved column every view-ray term's remainder beyond r falls as exp(-alpha r): alpha = c - c w_z / mu
    >= c for the single scattering looking level or down, c - K_J w_z >= (1 - MAX_GROWTH) c for J_ms (a seabed below
    makes J_ms grow with depth, bounded by `growth_floor` so that every direction a node is interpolated to keeps
    that), so open water minus the black surface falls at least as fast as exp(-(1 - MAX_GROWTH) c r), the model's
    own least rate, and reaches it to the last bit."""
    a, b = water
    sun = np.array([math.sqrt(1 - sun_z**2), 0.0, sun_z])
    lt = light(a, b, sun_dir=sun, e0=1.0, esky=esky, surface_z=depth)
    column = SolvedWater(medium=lt.medium, sun_dir_world=sun, sun=np.full(3, math.pi), sky=np.full(3, esky),
                         tables={(depth, True, True): random_table(seed, lt.medium.c)})
    lt = dataclasses.replace(lt, column=column, terms=dataclasses.replace(lt.terms, solved=True))
    black, limit = radiance_along(lt, down_or_level(data.draw), depth, RANGES)
    assert np.isfinite(black).all() and np.isfinite(limit).all()
    gap = limit - black
    scale = np.maximum(limit, 1e-300)
    assert (gap >= -1e-12 * scale).all()
    assert (np.diff(black, axis=0) >= -1e-12 * scale).all()
    c = lt.medium.c * (1.0 - MAX_GROWTH)
    bound = gap[0] * np.exp(-c[None, :] * (RANGES - RANGES[0])[:, None])
    assert (gap <= bound * (1 + 1e-9) + 1e-12 * scale).all()
    assert (gap[RANGES * c.min() > 40] <= 1e-15 * scale).all()


WATERS = {"coastal": ([0.35, 0.15, 0.12], [0.25, 0.3, 0.35]), "turbid": ([0.8, 0.2, 0.1], [1.5, 1.6, 1.8])}


@pytest.mark.parametrize("water", WATERS)
@pytest.mark.parametrize("depth", [3.0, 10.0])
def test_the_tables_path_radiance_is_the_columns_own_to_60_percent_and_13_percent_on_average(water, depth):
    """The twin's multiply scattered path radiance (J_ms at the camera, exponential in depth at K_J) against the
    column's own integral of its J_ms layer by layer along the ray (`column.path_radiance`, the solve's photon noise
    in one layer included), looking 60 degrees up to 60 down and round the sun's azimuth: the largest ratio within
    1.6 either way, the mean |log ratio| below 0.13."""
    a, b = (np.array(v) for v in WATERS[water])
    lt = with_column(light(a, b, sky=False, surface_z=depth + 1.0))
    medium, sun = lt.medium, lt.sun_dir_world
    el, az = np.meshgrid(np.radians([60, 30, 10, -10, -30, -60]), np.radians([0, 60, 120, 180]))
    az = az + math.atan2(sun[1], sun[0])
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    j_ms, k = lookup(lt.column.view_table(depth, True, False), dirs, sun)
    assert (k[dirs[:, 2] <= 0] >= 0).all() and (k <= medium.c).all() and (k >= -medium.c).all()
    for ch, (omega, g, mu) in enumerate(quantised(medium, float(sun[2]))):
        c = float(medium.c[ch])
        col = dataclasses.replace(full_column(omega, g, mu), e_sun=0.0)  # J_ms alone, on the whole view grid
        exact = math.pi * lt.sun_irradiance[ch] * path_radiance(col, to_sun_frame(dirs, sun), c * depth)
        wz = dirs[:, 2]
        to_surface = np.where(wz > 0, depth / np.where(wz > 0, wz, 1.0), np.inf)
        alpha = c - k[:, ch] * wz
        ours = j_ms[:, ch] / alpha * np.where(np.isfinite(to_surface), -np.expm1(-alpha * np.where(
            np.isfinite(to_surface), to_surface, 0.0)), 1.0)
        err = np.abs(np.log(ours / exact))
        assert err.max() < math.log(1.6) and err.mean() < 0.13


def test_the_table_is_the_unit_solve_scaled_by_the_light_and_a_pure_function_of_the_water():
    a, b = np.array([0.3, 0.1, 0.05]), np.array([0.05, 0.08, 0.1])
    lt = with_column(light(a, b, surface_z=9.0))
    twice = with_column(dataclasses.replace(lt, sun_irradiance=2 * lt.sun_irradiance, sky_irradiance=2 * lt.sky_irradiance))
    one, two = lt.column.view_table(6.0), twice.column.view_table(6.0)
    np.testing.assert_allclose(two.j, 2 * one.j, rtol=1e-12)
    np.testing.assert_array_equal(two.k, one.k)
    unit_column.cache_clear()  # solved again from nothing: the same numbers
    again = with_column(light(a, b, surface_z=9.0)).column.view_table(6.0)
    np.testing.assert_array_equal(again.j, one.j)
    np.testing.assert_array_equal(again.k, one.k)
    # jitter scales a and b together: b / c, and so the unit columns, stay; J_ms scales with c
    scaled = with_column(light(1.5 * a, 1.5 * b, surface_z=9.0 / 1.5 + 3.0)).column.view_table(6.0 / 1.5)
    np.testing.assert_allclose(scaled.j, 1.5 * one.j, rtol=1e-9)
    np.testing.assert_allclose(scaled.k, 1.5 * one.k, rtol=1e-9)


def test_without_scattering_the_table_is_empty_and_only_c_changes_the_view():
    lt = with_column(light(CLEAR, 0.0))
    table = lt.column.view_table(4.0)
    assert (table.j == 0).all()
    m = lt.medium
    np.testing.assert_array_equal(m.c, m.k)  # nothing scattered: c = K, so the frame is today's
    assert isinstance(m, Medium)


@pytest.mark.parametrize("solved", [False, True])
@pytest.mark.parametrize("lit", ["sun", "lamps"])
def test_a_frame_takes_the_solved_column_where_its_spec_asks_and_the_sun_or_sky_lights_it(solved, lit):
    """water.solved_column on (the default): frames lit by the sun or the sky take the column, lamp-only frames
    (nothing to solve) do not; off, no frame does, and every other draw of the frame is the same. The paper's model
    leaves the default alone (only setting it there is refused)."""
    from seasynth.service.spec.dataset import DatasetSpec

    assert DatasetSpec.model_validate({}).water.solved_column is True
    assert DatasetSpec.model_validate({"water": {"model": "paper"}}).water.resolved_model == "paper"
    from seasynth.worker.light.build import sample_physical
    from seasynth.worker.render import Lighting

    lighting = Lighting(np.array([0.3, 0.2, 0.93]), 1.0, 0.3) if lit == "sun" else Lighting(
        np.array([0.0, 0.0, -1.0]), 0.0, 0.0)
    lamps = [{"offset_m": [0.3, 0.0, 0.0], "direction": [0.0, 0.0, 1.0], "intensity": [2.0, 2.0]}]
    out = []
    for on in (False, solved):
        spec = DatasetSpec.model_validate({"water": {"model": "physical", "jerlov": ["II"], "solved_column": on},
                                           "lighting": {"lamps": lamps}})
        out.append(sample_physical(spec, np.random.default_rng(3), lighting, top_z=0.0)[0])
    off, lt = out
    takes = solved and lit == "sun"
    assert lt.terms.solved is takes and (lt.column is not None) is takes
    assert ("solved_column" in lt.terms.names()) is takes and ("solved_column" in lt.coefficients()) is takes
    assert dataclasses.replace(lt.terms, solved=False) == off.terms
    np.testing.assert_array_equal(lt.medium.a, off.medium.a)
    np.testing.assert_array_equal([lp.intensity for lp in lt.lamps], [lp.intensity for lp in off.lamps])
    assert for_spec(lt, False).terms == off.terms and for_spec(lt, False).column is None


@pytest.mark.parametrize("floor_z", [0.0, -20.0])  # 6 m deep, and 26 m: past the E_d table's last node
@pytest.mark.parametrize("which", ["sun", "sky"])
def test_a_floor_is_lit_by_the_solved_downwelling_irradiance(renderer, floor_z, which):
    """A grey floor under the sun straight above (no shadow maps) or under the sky alone: its J is albedo x E_d of
    the solved column at its depth (the sun's unscattered beam exp(-c D) plus the table's diffuse part; the sky's
    table), as `solved.irradiance` reads the table, to J's half-float storage."""
    floor = draw(f"test/solved/floor{floor_z}", quad([[-30, -30, floor_z], [30, -30, floor_z], [30, 30, floor_z],
                                                      [-30, 30, floor_z]], (200, 200, 200)), 0)
    a, b = np.array([0.2, 0.06, 0.05]), np.array([0.15, 0.25, 0.3])
    lt = with_column(light(a, b, sun=which == "sun", sky=which == "sky", sun_shadows=False, surface_z=6.0,
                           e0=np.full(3, 0.9), sun_dir=[0.0, 0.0, 1.0], esky=0.4))
    view, _ = camera([0.0, -4.0, floor_z + 3.0], [0.0, 0.0, floor_z], 60.0, far=100.0)
    J, R = renderer.samples(view, [floor], lt, ONE)
    seen = np.isfinite(R[0])
    assert seen.sum() > 1000
    depth = 6.0 - floor_z
    sun_diffuse, sky = irradiance(lt.column.depth_table(), np.array(depth))
    albedo = floor.mesh.albedo[0].astype(np.float64)
    if which == "sun":
        expected = albedo * 0.9 * (np.exp(-lt.medium.c * depth) + sun_diffuse)
        assert (sun_diffuse > 0).all()
    else:
        expected = albedo * 0.4 * sky
    np.testing.assert_allclose(J[0][seen].astype(np.float64), np.broadcast_to(expected, J[0][seen].shape), rtol=2e-3)


def test_the_solved_downwelling_is_todays_where_nothing_scatters_and_positive_where_it_does():
    lt = with_column(light(np.array([0.2, 0.06, 0.05]), np.array([0.0, 0.25, 0.3]), surface_z=8.0, e0=np.full(3, 0.9),
                           sun_dir=[0.0, 0.0, 1.0]))  # green and blue: the floor test's columns
    table = lt.column.depth_table()
    depth = np.linspace(0.0, 40.0, 81)
    sun_diffuse, sky = irradiance(table, depth)
    np.testing.assert_allclose(sky[:, 0], np.exp(-lt.medium.c[0] * depth / MU_SKY), rtol=1e-12)
    assert (sun_diffuse[:, 0] <= 1e-29).all() and (sun_diffuse[1:, 1:] > 0).all() and (sky[:, 1:] > 0).all()
    assert (sky[-1, 1:] < 0.05 * sky[0, 1:]).all()  # 40 m down, the water has taken most of the sky's light


def test_meta_records_the_solved_columns_only_where_a_frame_takes_them():
    lt = CASES["sun-sky-scattering"]
    assert "solved_column" not in lt.coefficients() and "solved_column" not in for_spec(lt, False).coefficients()
    record = for_spec(lt, True).coefficients()["solved_column"]
    assert record["columns"] == [list(q) for q in quantised(lt.medium, float(lt.sun_dir_world[2]))]
    assert set(record) == {"columns", "photons", "seed", "seabed"} and record["seabed"] is None  # none in this light


@settings(max_examples=60, deadline=None)
@given(water=waters(), data=st.data(), z=st.floats(0.0, 500.0), seed=st.integers(0, 2**32 - 1))
def test_solved_a_surface_is_seen_through_c_plus_the_water_in_front_of_it(water, data, z, seed):
    """With the solved column a surface's radiance J reaches the camera as J exp(-c z) (its forward-scattered light
    is not kept through K): the frame minus the same ray ending at a black surface is exactly that."""
    a, b = water
    lt = light(a, b, surface_z=30.0)
    column = SolvedWater(medium=lt.medium, sun_dir_world=lt.sun_dir_world, sun=np.full(3, 1.0), sky=np.full(3, 0.3),
                         tables={(29.0, True, True): random_table(seed, lt.medium.c)})
    lt = dataclasses.replace(lt, column=column, terms=dataclasses.replace(lt.terms, solved=True))
    d = down_or_level(data.draw)[None]
    J = np.array([[0.3, 0.5, 0.7]])
    black = volume(np.zeros((1, 3)), np.array([z]), d, d, 29.0, lt)
    seen = volume(J, np.array([z]), d, d, 29.0, lt) - black
    np.testing.assert_allclose(seen, J * np.exp(-lt.medium.c * z), rtol=1e-9, atol=1e-13 * black.max() + 1e-300)
