"""`seasynth calibrate` as a user runs it: the YAML it writes is a spec water: section, what it prints, and bad
files named on stderr with exit 1."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml
from calibration_helpers import B_INF, BETA_D, full_spec, photo
from PIL import Image


def seasynth(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("calibrate")
    image, z = photo()
    Image.fromarray(image).save(d / "photo.png")
    np.save(d / "range.npy", z.astype(np.float32))
    mm = np.where(np.isfinite(z), np.round(z * 1000), 0).astype(np.uint16)
    Image.fromarray(mm).save(d / "range_mm.png")
    return d


def test_calibrate_with_range_writes_a_water_section_the_spec_takes(files, tmp_path):
    out = tmp_path / "water.yaml"
    r = seasynth("calibrate", files / "photo.png", "--depth", files / "range.npy", "--out", out,
                 "--range-spread", "0")
    assert r.returncode == 0, r.stderr
    assert "water estimate (with range" in r.stdout and f"{out}: water section written" in r.stdout
    assert "beta_D       (1/m): R 0.3" in r.stdout
    text = out.read_text()
    assert text.startswith("# seasynth calibrate photo.png --depth range.npy\n")
    water = full_spec(yaml.safe_load(text)["water"]).water
    # spread 0: fixed water, the estimate itself (within the test_calibration tolerances of the truth).
    assert water.beta_D.min == water.beta_D.max and water.B_inf.min == water.B_inf.max
    assert np.abs(np.array(water.beta_D.min) - BETA_D).max() / BETA_D.min() <= 0.1
    assert np.abs(np.array(water.B_inf.min) - B_INF).max() <= 0.002


def test_calibrate_takes_a_16bit_png_range_map_in_millimetres(files):
    r = seasynth("calibrate", files / "photo.png", "--depth", files / "range_mm.png")
    assert r.returncode == 0, r.stderr
    # The PNG holds no +inf: no open water is seen, and the estimate says so.
    assert "0 of open water" in r.stdout and "no open water (range +inf) in view" in r.stdout
    water = full_spec(yaml.safe_load(r.stdout[r.stdout.index("water:\n"):])["water"]).water
    assert water.jerlov == [] and water.beta_D is not None


def test_calibrate_without_range_prints_what_is_not_identified(files):
    r = seasynth("calibrate", files / "photo.png", "--range-spread", "0.2")
    assert r.returncode == 0, r.stderr
    assert "beta_D       (1/m): R not identified, G not identified, B not identified" in r.stdout
    water = full_spec(yaml.safe_load(r.stdout[r.stdout.index("water:\n"):])["water"]).water
    assert len(water.jerlov) == 1 and water.beta_jitter == (0.8, 1.2)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("range.npy",), "error: {d}/range.npy: not an image Pillow can read"),
        (("missing.png",), "error: {d}/missing.png: cannot read"),
        (("photo.png", "--depth", "photo.png"), "error: {d}/photo.png: a RGB PNG cannot hold range"),
        (("photo.png", "--depth", "small.npy"), "error: {d}/small.npy: 3x2 does not match {d}/photo.png's 320x240"),
        (("photo.png", "--depth", "unmeasured.npy"), "error: {d}/unmeasured.npy: only 0 pixels have a usable finite "
                                                     "range"),
    ],
    ids=["photo-not-image", "photo-missing", "depth-8bit", "depth-size", "depth-unmeasured"],
)
def test_bad_files_are_named_on_stderr_with_exit_1(files, args, message):
    np.save(files / "small.npy", np.ones((2, 3), np.float32))
    np.save(files / "unmeasured.npy", np.full((240, 320), np.nan, np.float32))  # no pixel has a range
    r = seasynth("calibrate", *[files / a if not a.startswith("--") else a for a in args])
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip() == message.format(d=files) or r.stderr.startswith(message.format(d=files)), r.stderr
    assert "Traceback" not in r.stderr


def test_range_spread_outside_0_1_is_a_usage_error(files):
    r = seasynth("calibrate", files / "photo.png", "--range-spread", "1.5")
    assert r.returncode == 2 and "Invalid value for '--range-spread'" in r.stderr


def test_the_jerlov_prior_is_a_choice_that_needs_a_range_map(files):
    r = seasynth("calibrate", files / "photo.png", "--depth", files / "range.npy", "--prior", "jerlov",
                 "--range-spread", "0")
    assert r.returncode == 0, r.stderr
    assert "prior" in r.stdout.lower() and "jerlov" in r.stdout.lower()
    r = seasynth("calibrate", files / "photo.png", "--prior", "jerlov")
    assert r.returncode == 1 and "prior: 'jerlov' needs range_m" in r.stderr
    r = seasynth("calibrate", files / "photo.png", "--depth", files / "range.npy", "--prior", "sunny")
    assert r.returncode == 1 and "prior: need 'jerlov' or 'none'" in r.stderr


def test_range_spread_takes_what_the_api_takes_up_to_below_1(files, tmp_path):
    r = seasynth("calibrate", files / "photo.png", "--range-spread", "0.995", "--out", tmp_path / "w.yaml")
    assert r.returncode == 0, r.stderr
    r = seasynth("calibrate", files / "photo.png", "--range-spread", "1")
    assert r.returncode == 2 and "Invalid value for '--range-spread'" in r.stderr


def test_a_photo_name_with_a_line_break_keeps_the_written_yaml_valid(files, tmp_path):
    odd = tmp_path / "site\nwater: null\n.png"
    odd.write_bytes((files / "photo.png").read_bytes())
    out = tmp_path / "water.yaml"
    r = seasynth("calibrate", odd, "--out", out)
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert text.splitlines()[0] == "# seasynth calibrate site?water: null?.png"
    assert set(yaml.safe_load(text)) == {"water"} and yaml.safe_load(text)["water"]["enabled"] is True
