"""Marine snow in rendered frames: seeded, never labelled, occluding, lit by the lamps, unseen by sonar and
navigation, and free when off."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from local_datasets import same_across_workers_and_reproduce
from PIL import Image
from spec_helpers import EXAMPLE

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession

NIGHT_DIVE = EXAMPLE.parent / "night-dive.yaml"
SMALL = {"camera.width": 96, "camera.height": 72, "terrain.cells": 32, "quality": "fast", "outputs.instance": True,
         "outputs.range": True}
SNOW = {"water.particles.enabled": True, "water.particles.density_per_m3": [1500.0, 3000.0]}
# Dense, large and in turbid water (9C: the cut is short): a cloud that hides a good share of the view.
CLOUD = {"water.particles.enabled": True, "water.particles.density_per_m3": [3000.0, 3000.0],
         "water.particles.diameter_mm": [3.0, 6.0], "water.jerlov": ["9C"]}
SLOW = settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def session():
    with RenderSession() as s:
        yield s


def frames(spec, indices, session=None) -> list[dict[str, bytes]]:
    """Frame files from `session`, or from a session of their own."""
    if session is not None:
        return [session.frame_files(spec, i) for i in indices]
    with RenderSession() as s:
        return [s.frame_files(spec, i) for i in indices]


def png(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)))


def meta(files: dict[str, bytes], i: int) -> dict:
    return json.loads(files[f"meta/{i:06d}.json"])


@SLOW
@given(seed=st.integers(0, 2**31))
def test_particles_are_seeded_never_labelled_and_only_hide_what_they_cover(session, seed):
    """Two sessions draw the same bytes; against the frame without particles the instance image only loses ids
    (to 0) where particles cover it, each target keeps its unoccluded pixel count, its visible count never grows,
    and a label is written for every target left with visible pixels."""
    spec_on = load_spec(EXAMPLE, {**SMALL, **SNOW, "seed": seed, "frames": 2})
    spec_off = load_spec(EXAMPLE, {**SMALL, "seed": seed, "frames": 2})
    on, again, off = frames(spec_on, [0, 1]), frames(spec_on, [0, 1], session), frames(spec_off, [0, 1], session)
    assert on == again
    drawn = 0
    for i in (0, 1):
        n = f"{i:06d}"
        inst_on, inst_off = png(on[i][f"instance/{n}.png"]), png(off[i][f"instance/{n}.png"])
        assert np.all((inst_on == inst_off) | (inst_on == 0))
        m_on, m_off = meta(on[i], i), meta(off[i], i)
        record = m_on["optics"]["particles"]
        assert 1500.0 <= record["density_per_m3"] <= 3000.0 and record["diameter_mm"] == [0.5, 5.0]
        assert spec_on.camera.clip[0] < record["cut_m"][0] <= record["cut_m"][1] <= spec_on.camera.clip[1]
        drawn += record["count"]
        assert "optics" not in m_off
        for a, b in zip(m_on["objects"], m_off["objects"], strict=True):
            assert a["pixels_alone"] == b["pixels_alone"]
            assert (a["visible_pixels"] or 0) <= (b["visible_pixels"] or 0)
        lines = on[i][f"label_2/{n}.txt"].decode().splitlines()
        shown = [o for o in m_on["objects"] if o["role"] == "target" and o["visible_pixels"]]
        assert len(lines) == len(shown) == len(set(np.unique(inst_on)) - {0} & {o["instance_id"] for o in shown})
        if record["count"]:
            assert on[i][f"image_2/{n}.png"] != off[i][f"image_2/{n}.png"]
    assert drawn > 0


@SLOW
@given(seed=st.integers(0, 2**31))
def test_a_dense_cloud_hides_targets_and_lowers_their_visible_fraction(session, seed):
    spec_on = load_spec(EXAMPLE, {**SMALL, **CLOUD, "seed": seed, "frames": 1, "targets.count": [6, 8], "targets.scale": [2.5, 3.0]})
    spec_off = load_spec(EXAMPLE, {**SMALL, "water.jerlov": ["9C"], "seed": seed, "frames": 1,
                                   "targets.count": [6, 8], "targets.scale": [2.5, 3.0]})
    (on,), (off,) = frames(spec_on, [0], session), frames(spec_off, [0], session)
    objects = [(a, b) for a, b in zip(meta(on, 0)["objects"], meta(off, 0)["objects"])
               if b["role"] == "target" and b["visible_pixels"]]
    assert objects
    seen_on = sum(a["visible_pixels"] or 0 for a, _ in objects)
    assert seen_on < sum(b["visible_pixels"] for _, b in objects)
    # the visible fraction (visible over unoccluded pixels) of a target hidden entirely is 0
    fraction_on = sum((a["visible_pixels"] or 0) / b["pixels_alone"] for a, b in objects)
    assert fraction_on < sum(b["visible_pixels"] / b["pixels_alone"] for _, b in objects)
    # where the instance image changed, a particle stands in front: its range is nearer
    inst_on, inst_off = png(on["instance/000000.png"]), png(off["instance/000000.png"])
    r_on, r_off = (np.load(io.BytesIO(f["range/000000.npy"])) for f in (on, off))
    changed = inst_on != inst_off
    assert changed.any() and np.all(r_on[changed] < r_off[changed])


@pytest.mark.parametrize("seed", [0, 1])
def test_lamps_light_the_particles_near_the_camera(session, seed):
    """At night only the lamps light anything: particles in their beams near the camera are specks at full
    scale (the surface shader's light, clamped like every surface's), where the frame without them had less."""
    big = {"water.particles.density_per_m3": [1000.0, 1000.0], "water.particles.diameter_mm": [3.0, 8.0]}
    spec_on = load_spec(NIGHT_DIVE, {**SMALL, **SNOW, **big, "seed": seed, "frames": 1})
    spec_off = load_spec(NIGHT_DIVE, {**SMALL, "seed": seed, "frames": 1})
    (on,), (off,) = frames(spec_on, [0], session), frames(spec_off, [0], session)
    r_on, r_off = (np.load(io.BytesIO(f["range/000000.npy"])) for f in (on, off))
    particle = r_on < r_off - 0.05
    brightest = png(on["image_2/000000.png"]).max(axis=2)[particle].max()
    behind = png(off["image_2/000000.png"]).max(axis=2)[particle]
    assert brightest == 255 and behind.min() < 255


def test_off_changes_no_byte_and_sensors_never_see_particles(session):
    """Particle fields set but off: every file as without them. On: the sonar's and navigation's outputs and
    records are those of the frame without particles."""
    sensors = {"sensors.fls.enabled": True, "sensors.fls.beams": 32, "sensors.fls.range_bins": 32,
               "sensors.dvl.enabled": True, "sensors.pressure.enabled": True}
    base = {**SMALL, "frames": 2, **sensors}
    plain = frames(load_spec(EXAMPLE, base), [0, 1], session)
    off = frames(load_spec(EXAMPLE, {**base, "water.particles.density_per_m3": [9e4, 9e4],
                                     "water.particles.diameter_mm": [2.0, 3.0]}), [0, 1], session)
    assert off == plain
    on = frames(load_spec(EXAMPLE, {**base, **SNOW}), [0, 1], session)
    for i in (0, 1):
        assert meta(on[i], i)["optics"]["particles"]["count"] > 0
        sensor_files = {k for k in plain[i] if k.split("/")[0] not in
                        ("image_2", "instance", "range", "label_2", "calib", "meta")}
        assert any(k.startswith("fls") for k in sensor_files)
        assert all(on[i][k] == plain[i][k] for k in sensor_files)
        assert meta(on[i], i)["sensors"] == meta(plain[i], i)["sensors"]


@pytest.mark.parametrize("example", [EXAMPLE, NIGHT_DIVE], ids=["sun", "lamps"])
def test_particle_frames_are_the_same_across_workers_and_reproduce(tmp_path, example):
    spec = load_spec(example, {"camera.width": 48, "camera.height": 36, "frames": 2, "shard_size": 1,
                               "terrain.cells": 32, **SNOW})
    one = same_across_workers_and_reproduce(spec, tmp_path, 1)
    assert json.loads((one / "meta/000001.json").read_text())["optics"]["particles"]["count"] > 0
