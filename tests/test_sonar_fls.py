"""Forward-looking sonar: bins, shadows, aperture, the stated intensity law, speckle statistics, labels, determinism."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from local_datasets import seasynth, tree
from PIL import Image

from seasynth.service.spec.dataset import load_spec
from seasynth.service.spec.sensors import FLS, Acoustics
from seasynth.worker.frame.function import to_render_mesh
from seasynth.worker.local.generate import generate, reproduce
from seasynth.worker.render import DrawItem
from seasynth.worker.scene.poses import look_at_pose, rigid_inverse
from seasynth.worker.sensors.fls import (
    FULL_SCALE,
    absorption_db_per_m,
    fls_echo,
    fls_frame,
    fls_grid,
    fls_view,
    speckle_and_noise,
    to_uint16,
)

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
ACOUSTICS = Acoustics()
DEPTH_M = 10.0
# A small sonar: 64 beams over 60 deg, 64 bins over 0.5-20 m (0.305 m), no speckle unless a test asks.
SMALL = FLS(enabled=True, range_m=(0.5, 20.0), beams=64, range_bins=64, horizontal_aperture_deg=60.0, speckle=False)
EYE = np.array([0.0, 0.0, 2.0])  # the sonar 2 m above a flat seabed (z = 0), looking along +y, 11.3 deg down
POSE = look_at_pose(EYE, np.array([0.0, 10.0, 0.0]))


def item(mesh: trimesh.Trimesh, key: str, iid: int, at=(0.0, 0.0, 0.0), R=None) -> DrawItem:
    T = np.eye(4)
    T[:3, 3] = at
    if R is not None:
        T[:3, :3] = R
    return DrawItem(mesh=to_render_mesh(key, mesh), world_from_obj=T, albedo_scale=np.ones(3, np.float32),
                    albedo_bias=np.zeros(3, np.float32), instance_id=iid)


SEABED = trimesh.Trimesh(vertices=[[-40, -5, 0], [40, -5, 0], [40, 60, 0], [-40, 60, 0]], faces=[[0, 1, 2], [0, 2, 3]])


def sphere(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)


def facet(side: float) -> trimesh.Trimesh:
    """A square of `side` metres in its xz plane (normal -y, facing a sonar on -y)."""
    h = side / 2
    return trimesh.Trimesh(vertices=[[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], faces=[[0, 1, 2], [0, 2, 3]])


def echo(renderer, fls: FLS, items: list[DrawItem], objects: dict, pose=POSE):
    grid = fls_grid(fls)
    instance, range_m = renderer.geometry(fls_view(fls, grid, pose), items)
    rho = np.zeros(max(objects, default=0) + 1)
    rho[0] = fls.reflectivity_seabed
    for i, (role, _) in objects.items():
        rho[i] = fls.reflectivity_target if role == "target" else fls.reflectivity_distractor
    return fls_echo(fls, grid, range_m, instance, rho, absorption_db_per_m(fls.frequency_khz, ACOUSTICS, DEPTH_M))


def expected_cell(fls: FLS, point_world: np.ndarray, pose=POSE) -> tuple[float, float]:
    """(fractional range bin, fractional beam) of a world point."""
    p = (rigid_inverse(pose) @ np.r_[point_world, 1.0])[:3]
    r, az = float(np.linalg.norm(p)), math.degrees(math.atan2(p[0], p[2]))
    dr = (fls.range_m[1] - fls.range_m[0]) / fls.range_bins
    spacing = fls.horizontal_aperture_deg / fls.beams
    return (r - fls.range_m[0]) / dr, (az + fls.horizontal_aperture_deg / 2) / spacing - 0.5


def test_absorption_follows_francois_garrison():
    # Francois-Garrison 1982 at 10 C, 35 ppt, pH 8, 0 m: 100 kHz ~ 0.034 dB/m (the pure-water term dominates
    # from ~500 kHz, ~f^2): the formula as coded, pinned against values computed by hand from its terms.
    a100 = absorption_db_per_m(100.0, ACOUSTICS, 0.0)
    a750 = absorption_db_per_m(750.0, ACOUSTICS, 0.0)
    assert 0.030 < a100 < 0.040
    assert 0.20 < a750 < 0.24
    assert absorption_db_per_m(750.0, ACOUSTICS, 1000.0) < a750  # pressure lowers absorption


@pytest.mark.parametrize("narrow", [
    dict(beams=32, horizontal_aperture_deg=60.0, beam_width_deg=0.1, beam_pattern="gaussian"),
    dict(beams=2, horizontal_aperture_deg=10.0, beam_width_deg=0.05, beam_pattern="sinc2"),
    dict(beams=64, horizontal_aperture_deg=60.0, beam_width_deg=0.2, beam_pattern="gaussian"),
    dict(beams=64, horizontal_aperture_deg=60.0, beam_width_deg=2.0, beam_pattern="sinc2"),
])
def test_a_uniform_sphere_fills_every_beam_with_the_stated_intensity(narrow):
    # Every pixel 5 m away (the inside of a sphere about the sonar: normal incidence, one range bin), no TVG: each
    # beam's echo is rho 10^(-2 alpha r/10) r^-2 exactly, its pattern normalised by its own solid angle. Beams much
    # narrower than their spacing used to fall between the azimuth sub-bins' centres: 0/0 weights, NaN, a black image.
    fls = FLS(enabled=True, range_m=(0.5, 20.0), range_bins=16, vertical_aperture_deg=1.0, tvg=False, speckle=False,
              **narrow)
    assert np.isfinite(fls_grid(fls).W).all()
    r, alpha = 5.0, 0.2
    e = uniform_sphere(fls, r, alpha)
    k = int((r - 0.5) / (19.5 / 16))
    assert e.intensity[k] == pytest.approx(np.full(fls.beams, 0.3 * 10 ** (-alpha * r / 5) / r**2), rel=1e-5)
    assert np.count_nonzero(e.intensity) == fls.beams


def uniform_sphere(fls: FLS, r: float, alpha: float, range_m: np.ndarray | None = None):
    """fls_echo of a render whose every pixel sees the seabed (rho 0.3) r metres away (the inside of a sphere about
    the sonar: normal incidence), or at range_m (h, w) float32 metres."""
    grid = fls_grid(fls)
    shape = (grid.height, grid.width)
    ranges = np.full(shape, r, np.float32) if range_m is None else range_m
    return fls_echo(fls, grid, ranges, np.zeros(shape, np.uint32), np.array([0.3]), alpha)


TVG_LONG = FLS(enabled=True, range_m=(0.5, 500.0), range_bins=64, beams=16, horizontal_aperture_deg=30.0,
               beam_width_deg=2.0, vertical_aperture_deg=5.0, speckle=False, noise_sigma=0.01)


@pytest.mark.parametrize("frequency_khz", [750.0, 3000.0])
def test_tvg_restores_a_uniform_sphere_at_any_range_and_keeps_the_noise(frequency_khz):
    # At a bin centre TVG undoes r^-2 and absorption exactly: every beam of that bin reads rho. At 3 MHz in -2 C
    # water (alpha 4.9 dB/m) the bins' gain 10^(alpha r / 5) overflowed past ~310 m and inf * 0 made every empty bin
    # NaN, which the 16-bit codes turned to 0, noise and all.
    fls = TVG_LONG.model_copy(update={"frequency_khz": frequency_khz})
    alpha = absorption_db_per_m(frequency_khz, Acoustics(temperature_c=-2.0), 0.0)
    edges = fls_grid(fls).range_edges
    k = 57
    e = uniform_sphere(fls, (edges[k] + edges[k + 1]) / 2, alpha)
    assert np.isfinite(e.intensity).all()
    assert e.intensity[k] == pytest.approx(np.full(fls.beams, 0.3), rel=1e-5)
    assert np.count_nonzero(e.intensity) == fls.beams
    codes = to_uint16(speckle_and_noise(e.intensity, fls, np.random.default_rng(0)))
    empty = np.delete(codes, k, axis=0)
    assert np.mean(empty > 0) == pytest.approx(0.5, abs=0.1)  # max(N(0, sigma), 0) > 0 half the time


def test_tvg_folded_into_the_bins_equals_the_plain_gain(monkeypatch):
    # A seabed-like ramp of ranges (footprints spread pixels over several bins) at 750 kHz, where the plain gain is
    # sound: the folded TVG (log space, per pixel and bin) gives the same bins to rounding.
    import seasynth.worker.sensors.fls as fls_module

    fls = TVG_LONG.model_copy(update={"range_m": (0.5, 40.0)})
    grid = fls_grid(fls)
    ramp = np.linspace(1.0, 39.0, grid.height, dtype=np.float32)[:, None].repeat(grid.width, 1)
    alpha = absorption_db_per_m(fls.frequency_khz, ACOUSTICS, DEPTH_M)
    plain = uniform_sphere(fls, 0.0, alpha, ramp).intensity
    monkeypatch.setattr(fls_module, "TVG_PLAIN_MAX_DECADES", 0.0)
    folded = uniform_sphere(fls, 0.0, alpha, ramp).intensity
    assert np.count_nonzero(plain) > fls.beams * 30
    assert np.array_equal(folded > 0, plain > 0)
    assert np.allclose(folded, plain, rtol=1e-9, atol=0.0)


def test_sphere_lands_in_its_bin_and_shadows_the_seabed_behind_it(renderer):
    fls = SMALL.model_copy(update={"beam_pattern": "gaussian"})
    radius, centre = 0.6, np.array([2.0, 10.0, 0.6])
    with_sphere = echo(renderer, fls, [item(SEABED, "seabed", 0), item(sphere(radius), "sphere.6", 1, centre)],
                       {1: ("target", "Sphere")})
    bare = echo(renderer, fls, [item(SEABED, "seabed", 0)], {})
    bin_c, beam_c = expected_cell(fls, centre)
    dr = (fls.range_m[1] - fls.range_m[0]) / fls.range_bins
    front = bin_c - radius / dr  # the sphere's nearest point (normal incidence: its brightest echo)
    cells = with_sphere.cell_of[1]
    peak = cells[np.argmax(with_sphere.intensity[cells[:, 0], cells[:, 1]])]
    assert abs(peak[0] - front) <= 1.0 and abs(peak[1] - beam_c) <= 1.0
    # Behind it at its beam: seabed echoes without the sphere, exactly none with it (from just past its far side
    # to 3 m before the shadow ends, where the grazing ray over its top meets the seabed).
    b = int(round(beam_c))
    p = (rigid_inverse(POSE) @ np.r_[centre, 1.0])[:3]
    top = centre + [0, 0, radius]
    end_horizontal = np.hypot(*top[:2]) * EYE[2] / (EYE[2] - top[2])
    end_bin = (math.hypot(end_horizontal, EYE[2]) - 3.0 - fls.range_m[0]) / dr
    shadow = slice(int(math.ceil(bin_c + radius / dr + 1)), int(end_bin))
    assert shadow.stop - shadow.start >= 5 and np.linalg.norm(p) > 0
    assert np.all(bare.intensity[shadow, b] > 0)
    assert np.all(with_sphere.intensity[shadow, b] == 0)


def test_target_outside_the_aperture_gives_no_return_and_no_label(renderer):
    centre = np.array([12.0, 10.0, 0.6])  # bearing ~50 deg: outside +-30
    assert abs(expected_cell(SMALL, centre)[1]) > SMALL.beams
    seen = echo(renderer, SMALL, [item(SEABED, "seabed", 0), item(sphere(0.6), "sphere.6", 1, centre)],
                {1: ("target", "Sphere")})
    bare = echo(renderer, SMALL, [item(SEABED, "seabed", 0)], {})
    assert seen.cell_of == {}
    assert np.array_equal(seen.intensity, bare.intensity)
    fr = fls_frame(SMALL, ACOUSTICS, renderer, [item(SEABED, "seabed", 0), item(sphere(0.6), "sphere.6", 1, centre)],
                   POSE, {1: ("target", "Sphere")}, DEPTH_M, np.random.default_rng(0))
    assert fr.labels == []


def _facets_total(renderer, fls, ranges, tilt_deg=(0.0, 0.0)):
    """Summed intensity of identical 1 m facets at the sonar's height, at `ranges` and bearings -12 and +12 deg,
    facing the sonar then tilted about their vertical axis; no seabed. Returns the two sums."""
    eye = np.array([0.0, 0.0, 5.0])
    pose = look_at_pose(eye, eye + [0.0, 1.0, 0.0])
    items, objects = [], {}
    for i, (r, bearing, tilt) in enumerate(zip(ranges, (-12.0, 12.0), tilt_deg), start=1):
        b = math.radians(bearing)
        at = eye + r * np.array([math.sin(b), math.cos(b), 0.0])
        yaw = -b + math.radians(tilt)  # normal -y turned to face the sonar, then tilted
        R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1.0]])
        items.append(item(facet(1.0), "facet1", i, at, R))
        objects[i] = ("target", None)
    e = echo(renderer, fls, items, objects, pose)
    half = fls.beams // 2
    return float(e.intensity[:, :half].sum()), float(e.intensity[:, half:].sum())


LAW = FLS(enabled=True, range_m=(0.5, 20.0), beams=80, range_bins=64, horizontal_aperture_deg=40.0,
          vertical_aperture_deg=60.0, beam_width_deg=0.5, beam_pattern="gaussian", tvg=False, speckle=False)


def test_intensity_falls_with_range_as_the_stated_law(renderer):
    # A facet of fixed size: r^-2 per solid angle times a solid angle ~ r^-2, so r^-4, times two-way absorption.
    # The facets sit at bin centres (bins 14 and 31, ~5 and ~10 m) so TVG, applied at bin centres, is exact.
    dr = (LAW.range_m[1] - LAW.range_m[0]) / LAW.range_bins
    r1, r2 = LAW.range_m[0] + 14.5 * dr, LAW.range_m[0] + 31.5 * dr
    near, far = _facets_total(renderer, LAW, (r1, r2))
    alpha = absorption_db_per_m(LAW.frequency_khz, ACOUSTICS, DEPTH_M)
    law = (r2 / r1) ** 4 * 10 ** (2 * alpha * (r2 - r1) / 10)
    # 5%: the facets' solid angles are counted in render pixels (the far one is ~34 pixels a side) and the
    # vertical pattern weighs the near facet's +-5.7 deg ~1% less than the far one's +-2.9 deg (measured: 3% low).
    assert near / far == pytest.approx(law, rel=0.05)
    # TVG undoes r^2 and absorption: what is left is the facets' solid-angle ratio, (r2 / r1)^2.
    tvg_near, tvg_far = _facets_total(renderer, LAW.model_copy(update={"tvg": True}), (r1, r2))
    assert tvg_near / tvg_far == pytest.approx((r2 / r1) ** 2, rel=0.05)


def test_normal_incidence_is_brighter_than_grazing(renderer):
    facing, tilted = _facets_total(renderer, LAW, (6.0, 6.0), tilt_deg=(0.0, 60.0))
    # cos^n(60 deg) with n = 1, times the tilted facet's solid angle (cos 60 deg as large): 1/4.
    assert tilted < facing
    assert tilted / facing == pytest.approx(math.cos(math.radians(60)) ** 2, rel=0.1)


def test_speckle_and_noise_match_their_stated_distributions(renderer):
    fls = FLS(enabled=True, range_m=(0.5, 20.0), beams=128, range_bins=256, horizontal_aperture_deg=90.0,
              beam_width_deg=1.0)
    clean = echo(renderer, fls, [item(SEABED, "seabed", 0)], {}).intensity
    lit = clean > 0
    assert lit.sum() > 10_000
    for looks in (1.0, 4.0):
        got = speckle_and_noise(clean, fls.model_copy(update={"speckle_looks": looks}), np.random.default_rng(1))
        s = got[lit] / clean[lit]
        n = s.size
        # Gamma(L, 1/L): mean 1, variance 1/L; 4 standard errors (variance's: sqrt((6/L + 2) / L^2 / n)).
        assert s.mean() == pytest.approx(1.0, abs=4 / math.sqrt(looks * n))
        assert s.var() == pytest.approx(1 / looks, abs=4 * math.sqrt((6 / looks + 2) / looks**2 / n))
        assert np.all(got[~lit] == 0)
    sigma = 0.01
    got = speckle_and_noise(clean, fls.model_copy(update={"speckle": False, "noise_sigma": sigma}),
                            np.random.default_rng(2))
    dark = got[~lit]
    # max(N, 0), N ~ Normal(0, sigma): half exactly 0, mean sigma / sqrt(2 pi).
    assert np.mean(dark == 0) == pytest.approx(0.5, abs=4 * 0.5 / math.sqrt(dark.size))
    assert dark.mean() == pytest.approx(sigma / math.sqrt(2 * math.pi), rel=0.05)
    assert np.array_equal(to_uint16(np.array([-1.0, 0.0, 0.5, 1.0, 2.0])),
                          np.array([0, 0, 32768, FULL_SCALE, FULL_SCALE], np.uint16))


@settings(max_examples=60, deadline=None)
@given(looks=st.one_of(st.sampled_from([5e-324, 1e-310, 5.6e-309, 1e-300, 1.0, 1e6]), st.floats(5e-324, 1e6)),
       noise=st.sampled_from([0.0, 0.01]), seed=st.integers(0, 2**32 - 1))
def test_speckle_of_any_looks_is_finite_keeps_no_echo_dark_and_draws_numpys_gamma(looks, noise, seed):
    """speckle_looks may be any float > 0: below 5.6e-309, 1 / L is inf and the speckle saturates the cells it
    lights; the codes stay finite, a cell with no echo gets no speckle, and elsewhere the draw is Gamma(L, 1/L)
    exactly as numpy's gamma gives it (the sonar examples keep their bytes)."""
    intensity = np.random.default_rng(seed).uniform(0.0, 2.0, (8, 6)) * (np.arange(6) % 3 > 0)
    fls = FLS(enabled=True, speckle_looks=looks, noise_sigma=noise)
    got = speckle_and_noise(intensity, fls, np.random.default_rng(seed))
    assert not np.isnan(got).any() and np.all(got >= 0)
    assert np.array_equal(to_uint16(got) == FULL_SCALE, got >= 1.0 - 0.5 / FULL_SCALE)  # inf: full scale
    if noise == 0:
        assert np.all(got[intensity == 0] == 0) and np.all(np.isfinite(got) | (intensity > 0))
    if 1.0 / looks < math.inf and noise == 0:
        want = np.maximum(intensity * np.random.default_rng(seed).gamma(looks, 1.0 / looks, intensity.shape), 0.0)
        assert np.array_equal(got, want)


# ---- end to end: generate, labels, determinism -------------------------------------------------------------------
# No additive noise, so every nonzero cell is an echo (speckle, on by default, still draws from the FLS stream).
FLS_ON = {"camera.width": 32, "camera.height": 24, "frames": 4, "shard_size": 2, "sensors.fls.enabled": True,
          "sensors.fls.beams": 64, "sensors.fls.range_bins": 64, "sensors.fls.range_m": [0.3, 6.0]}


@pytest.fixture(scope="module")
def fls_dataset(tmp_path_factory) -> tuple[Path, object]:
    spec = load_spec(EXAMPLE, FLS_ON)
    out = tmp_path_factory.mktemp("fls")
    generate(spec, out, workers=1)
    return out, spec


def test_every_labelled_target_has_returns_inside_its_boxes(fls_dataset):
    out, spec = fls_dataset
    labelled = 0
    for i in range(spec.frames):
        n = f"{i:06d}"
        polar = np.asarray(Image.open(out / f"fls/{n}.png"))
        fan = np.asarray(Image.open(out / f"fls_fan/{n}.png"))
        assert polar.dtype == np.uint16 and polar.shape == (64, 64)
        meta = json.loads((out / f"meta/{n}.json").read_text())
        assert list(fan.shape[::-1]) == meta["sensors"]["fls"]["fan_size"]
        targets = {o["instance_id"] for o in meta["objects"] if o["role"] == "target"}
        for obj in json.loads((out / f"fls_label/{n}.json").read_text())["objects"]:
            assert obj["instance_id"] in targets and obj["class"] == "Urchin"
            pb, fb = obj["polar_box"], obj["fan_box"]
            assert polar[pb["bin_min"]: pb["bin_max"] + 1, pb["beam_min"]: pb["beam_max"] + 1].max() > 0
            assert fan[fb["top"]: fb["bottom"] + 1, fb["left"]: fb["right"] + 1].max() > 0
            labelled += 1
    assert labelled > 0


def test_fls_is_deterministic_across_workers_shards_and_reproduce(fls_dataset, tmp_path):
    out, spec = fls_dataset
    two = tmp_path / "two"
    generate(load_spec(EXAMPLE, {**FLS_ON, "shard_size": 3}), two, workers=2)
    a, b = tree(two), tree(out)
    a.pop("seasynth.json"), b.pop("seasynth.json")
    assert a == b
    paths = reproduce(spec, 2, tmp_path / "one")
    assert any(p.startswith("fls/") for p in paths)
    for rel in paths:
        assert (tmp_path / "one" / rel).read_bytes() == (out / rel).read_bytes(), rel


def test_fls_changes_no_camera_byte(fls_dataset, tmp_path):
    out, spec = fls_dataset
    off = {k: v for k, v in FLS_ON.items() if not k.startswith("sensors.")}
    generate(load_spec(EXAMPLE, off), tmp_path, workers=1)
    for i in range(spec.frames):
        n = f"{i:06d}"
        for rel in (f"image_2/{n}.png", f"label_2/{n}.txt", f"calib/{n}.txt"):
            assert (tmp_path / rel).read_bytes() == (out / rel).read_bytes(), rel
        with_fls = json.loads((out / f"meta/{n}.json").read_text())
        assert set(with_fls.pop("sensors")) == {"fls"}
        assert with_fls == json.loads((tmp_path / f"meta/{n}.json").read_text())
    assert not (tmp_path / "fls").exists()


def test_the_survey_example_generates_with_the_cli(tmp_path):
    example = EXAMPLE.parent / "survey-sonar.yaml"
    done = seasynth("generate", example, "--out", tmp_path, "--frames", "2", "--width", "32", "--height", "24")
    assert done.returncode == 0, done.stderr
    spec = load_spec(example)
    for i in range(2):
        n = f"{i:06d}"
        polar = np.asarray(Image.open(tmp_path / f"fls/{n}.png"))
        assert polar.shape == (spec.sensors.fls.range_bins, spec.sensors.fls.beams) and polar.max() > 0
        nav = json.loads((tmp_path / f"nav/{n}.json").read_text())
        assert set(nav) >= {"dvl", "pressure", "imu"} and nav["dvl"]["bottom_lock"]
        assert nav["velocity_world_m_s"] == [spec.trajectory.speed_m_s, 0.0, pytest.approx(0.0, abs=0.06)]
        assert json.loads((tmp_path / f"fls_label/{n}.json").read_text())["objects"]


def test_fan_boxes_hold_every_fan_pixel_of_their_cells(renderer):
    from seasynth.worker.sensors.fan import fan_geometry

    items = [item(SEABED, "seabed", 0), item(sphere(0.6), "sphere.6", 1, np.array([2.0, 10.0, 0.6])),
             item(sphere(0.3), "sphere.3", 2, np.array([-2.5, 7.0, 0.3]))]
    objects = {1: ("target", "Sphere"), 2: ("target", "Sphere")}
    fr = fls_frame(SMALL, ACOUSTICS, renderer, items, POSE, objects, DEPTH_M, np.random.default_rng(0))
    e = echo(renderer, SMALL, items, objects)
    fan = fan_geometry(SMALL)
    assert [lb["instance_id"] for lb in fr.labels] == [1, 2]
    for lb in fr.labels:
        cells = e.cell_of[lb["instance_id"]]
        mask = np.zeros((SMALL.range_bins, SMALL.beams), bool)
        mask[cells[:, 0], cells[:, 1]] = True
        rows, cols = np.nonzero(fan.inside & mask[fan.bin, fan.beam])
        assert rows.size > 0
        fb, pb = lb["fan_box"], lb["polar_box"]
        assert fb["top"] <= rows.min() and rows.max() <= fb["bottom"]
        assert fb["left"] <= cols.min() and cols.max() <= fb["right"]
        # The box is the cells' sectors' bounding box: at most 2 pixels wider than the pixels found on each side.
        assert rows.min() - fb["top"] <= 2 and fb["bottom"] - rows.max() <= 2
        assert cols.min() - fb["left"] <= 2 and fb["right"] - cols.max() <= 2
        assert (pb["bin_min"], pb["bin_max"]) == (cells[:, 0].min(), cells[:, 0].max())
        assert (pb["beam_min"], pb["beam_max"]) == (cells[:, 1].min(), cells[:, 1].max())
