"""Side-scan sonar: nadir gap, target bin and shadow, the other side untouched, waterfall of a track, determinism."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from seasynth.service.spec.dataset import load_spec
from seasynth.service.spec.sensors import SSS, Acoustics
from seasynth.worker.frame.function import to_render_mesh
from seasynth.worker.local.generate import generate, reproduce
from seasynth.worker.render import DrawItem
from seasynth.worker.scene.poses import look_at_pose
from seasynth.worker.sensors.fls import absorption_db_per_m
from seasynth.worker.sensors.sss import side_echo, sss_frame, sss_grid, waterfall

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
SONAR = SSS(enabled=True, range_m=15.0, range_bins=128, speckle=False)  # bins of 0.117 m
DR = SONAR.range_m / SONAR.range_bins
ALTITUDE = 3.0
RADIUS, CENTRE = 0.5, np.array([6.0, 0.0, 0.5])  # a sphere on the seabed 6 m to starboard of the track x = 0


def item(mesh, key: str, iid: int, at=(0.0, 0.0, 0.0)) -> DrawItem:
    T = np.eye(4)
    T[:3, 3] = at
    return DrawItem(mesh=to_render_mesh(key, mesh), world_from_obj=T, albedo_scale=np.ones(3, np.float32),
                    albedo_bias=np.zeros(3, np.float32), instance_id=iid)


SEABED = trimesh.Trimesh(vertices=[[-40, -40, 0], [40, -40, 0], [40, 40, 0], [-40, 40, 0]],
                         faces=[[0, 1, 2], [0, 2, 3]])


def ping(renderer, y: float, with_sphere: bool = True):
    """One ping from (0, y, ALTITUDE), level, heading +y."""
    items = [item(SEABED, "sss-seabed", 0)]
    if with_sphere:
        items.append(item(trimesh.creation.icosphere(subdivisions=4, radius=RADIUS), "sss-sphere", 1, CENTRE))
    eye = np.array([0.0, y, ALTITUDE])
    return sss_frame(SONAR, Acoustics(), renderer, items, look_at_pose(eye, eye + [0.0, 1.0, 0.0]),
                     {1: ("target", "Sphere")} if with_sphere else {}, 10.0, np.random.default_rng(0))


def test_nadir_gap_target_bin_shadow_and_untouched_port_side(renderer):
    n = SONAR.range_bins
    fr = ping(renderer, 0.0)
    bare = ping(renderer, 0.0, with_sphere=False)
    port, starboard = fr.row[0, :n][::-1], fr.row[0, n:]  # both near to far
    # Nadir gap: no echo before the seabed directly below (the render reaches 89 deg: first echo ~ALTITUDE).
    first = int(ALTITUDE / DR)
    for side in (port, starboard):
        assert np.all(side[:first] == 0) and np.all(side[first + 1: first + 10] > 0)
    # The sphere's nearest point at normal incidence: the brightest starboard bin, within one bin.
    front = (math.hypot(CENTRE[0], ALTITUDE - CENTRE[2]) - RADIUS) / DR
    assert abs(int(np.argmax(starboard)) - front) <= 1.0
    # Its shadow: from behind it to 1 m before the grazing ray over its top meets the seabed, nothing comes back.
    top = CENTRE[2] + RADIUS
    end = math.hypot(CENTRE[0] * ALTITUDE / (ALTITUDE - top), ALTITUDE)
    shadow = slice(int(math.ceil((math.hypot(CENTRE[0], ALTITUDE - CENTRE[2]) + RADIUS) / DR)), int((end - 1) / DR))
    assert shadow.stop - shadow.start >= 5
    assert np.all(starboard[shadow] == 0) and np.all(bare.row[0, n:][shadow] > 0)
    assert np.array_equal(fr.row[0, :n], bare.row[0, :n])  # the port side never sees it
    (label,) = fr.labels
    assert label["side"] == "starboard" and label["instance_id"] == 1
    assert label["column_min"] == n + label["bin_min"] and label["bin_min"] <= np.argmax(starboard) <= label["bin_max"]


def test_a_waterfall_shows_the_target_only_while_it_is_abeam(renderer):
    ys = np.round(np.arange(-2.0, 2.01, 0.25), 2)
    frames = [ping(renderer, float(y)) for y in ys]
    bare = ping(renderer, 0.0, with_sphere=False).row
    wf = waterfall([f.row for f in frames])
    assert wf.shape == (len(ys), 2 * SONAR.range_bins) and wf.dtype == np.uint16
    # Along-track beam: +-2 beam widths (+-1 deg) at ~6.5 m is +-0.11 m; with the sphere's radius, |y| < 0.62 m.
    reach = RADIUS + 6.5 * math.tan(math.radians(2 * SONAR.horizontal_beam_deg))
    for y, f, row in zip(ys, frames, wf):
        if abs(y) > reach:
            assert np.array_equal(row, bare[0]) and f.labels == []
        elif abs(y) < RADIUS:
            assert [lb["instance_id"] for lb in f.labels] == [1]


SURVEY = {"camera.width": 32, "camera.height": 24, "frames": 4, "shard_size": 3, "trajectory.kind": "lawnmower",
          "sensors.sss.enabled": True, "sensors.sss.range_bins": 64, "sensors.sss.range_m": 8.0,
          "sensors.sss.pose.pitch_deg": -30.0, "sensors.sss.noise_sigma": 0.001}


def test_sss_files_are_deterministic_and_change_no_camera_byte(tmp_path):
    spec = load_spec(EXAMPLE, SURVEY)
    one, two = tmp_path / "one", tmp_path / "two"
    generate(spec, one, workers=1)
    generate(load_spec(EXAMPLE, {**SURVEY, "shard_size": 1}), two, workers=2)
    off = tmp_path / "off"
    generate(load_spec(EXAMPLE, {k: v for k, v in SURVEY.items() if not k.startswith("sensors.")}), off, workers=1)
    rows = []
    for i in range(spec.frames):
        n = f"{i:06d}"
        row = np.asarray(Image.open(one / f"sss/{n}.png"))
        assert row.shape == (1, 128) and row.dtype == np.uint16 and row.max() > 0
        rows.append(row)
        for rel in (f"sss/{n}.png", f"sss_label/{n}.json", f"meta/{n}.json"):
            assert (one / rel).read_bytes() == (two / rel).read_bytes(), rel
        for rel in (f"image_2/{n}.png", f"label_2/{n}.txt", f"calib/{n}.txt"):
            assert (one / rel).read_bytes() == (off / rel).read_bytes(), rel
        assert set(json.loads((one / f"meta/{n}.json").read_text())["sensors"]) == {"sss"}
    assert waterfall(rows).shape == (spec.frames, 128)
    for rel in reproduce(spec, 3, tmp_path / "again"):
        assert (tmp_path / "again" / rel).read_bytes() == (one / rel).read_bytes(), rel


def test_speckle_draws_come_from_the_sss_stream(renderer):
    # Same scene, two generators: the clean line is the same, the speckled ones differ; seed 0 twice is identical.
    speckled = SONAR.model_copy(update={"speckle": True})
    items = [item(SEABED, "sss-seabed", 0)]
    eye = np.array([0.0, 0.0, ALTITUDE])
    pose = look_at_pose(eye, eye + [0.0, 1.0, 0.0])
    a, b, c = (sss_frame(speckled, Acoustics(), renderer, items, pose, {}, 10.0, np.random.default_rng(s)).row
               for s in (0, 0, 1))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    n, gap = SONAR.range_bins, int(ALTITUDE / DR)
    for row in (a, c):  # speckle multiplies: the nadir gap stays exactly 0 on both sides
        assert np.all(row[0, n - gap: n + gap] == 0)


@pytest.mark.parametrize("frequency_khz", [900.0, 3000.0])
def test_tvg_restores_a_uniform_sphere_at_long_range_and_high_frequency(frequency_khz):
    # Every pixel sees the seabed (rho 0.3) at one bin's centre range: TVG undoes r^-2 and absorption exactly, so
    # that bin reads rho and every other 0. At 3 MHz in -2 C water (alpha 4.9 dB/m) the plain gain 10^(alpha r / 5)
    # overflowed past ~310 m: inf * 0 = NaN in every empty bin.
    sss = SSS(enabled=True, range_m=500.0, range_bins=64, frequency_khz=frequency_khz, speckle=False)
    grid = sss_grid(sss)
    alpha = absorption_db_per_m(frequency_khz, Acoustics(temperature_c=-2.0), 0.0)
    k = 57
    shape = (grid.height, grid.width)
    ranges = np.full(shape, (grid.edges[k] + grid.edges[k + 1]) / 2, np.float32)
    line, _ = side_echo(sss, grid, ranges, np.zeros(shape, np.uint32), np.array([0.3]), alpha)
    assert np.isfinite(line).all()
    assert line[k] == pytest.approx(0.3, rel=1e-5) and np.count_nonzero(line) == 1
