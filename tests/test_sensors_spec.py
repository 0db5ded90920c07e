"""The spec's sensors and trajectory sections: off by default, absent from the digest, errors naming the field."""

from __future__ import annotations

import pytest

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import DatasetSpec, parse_spec, spec_digest
from seasynth.service.spec.sensors import FLS, MAX_FLS_FAN_PIXELS, MAX_FLS_FAN_SIDE, Sensors


def test_every_sensor_is_off_by_default_and_leaves_the_digest_alone():
    spec = DatasetSpec()
    s = spec.sensors
    assert not (s.fls.enabled or s.sss.enabled or s.dvl.enabled or s.pressure.enabled or s.imu.enabled)
    assert spec.trajectory.kind == "random"
    dumped = spec.model_dump(mode="json", exclude_defaults=True)
    assert "sensors" not in dumped and "trajectory" not in dumped
    assert spec_digest(parse_spec({"sensors": {}, "trajectory": {"kind": "random"}})) == spec_digest(spec)
    assert spec_digest(parse_spec({"sensors": {"fls": {"enabled": True}}})) != spec_digest(spec)


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"sensors": {"fls": {"range_m": [5.0, 1.0]}}}, "sensors.fls.range_m"),
        ({"sensors": {"fls": {"range_m": [0.0, 1.0]}}}, "sensors.fls.range_m"),
        ({"sensors": {"fls": {"range_m": [0.5, 501.0]}}}, "sensors.fls.range_m"),
        ({"sensors": {"fls": {"beams": 1}}}, "sensors.fls.beams"),
        ({"sensors": {"fls": {"beam_pattern": "box"}}}, "sensors.fls.beam_pattern"),
        ({"sensors": {"fls": {"beam_width_deg": 131.0, "horizontal_aperture_deg": 130.0}}}, "sensors.fls"),
        ({"sensors": {"fls": {"beams": 1024, "horizontal_aperture_deg": 170.0, "beam_width_deg": 0.1}}},
         "sensors.fls"),
        ({"sensors": {"fls": {"enabled": 1}}}, "sensors.fls.enabled"),
        ({"sensors": {"fls": {"gain": 3.0}}}, "sensors.fls.gain"),
        ({"sensors": {"dvl": {"beam_angle_deg": 90.0}}}, "sensors.dvl.beam_angle_deg"),
        ({"sensors": {"pressure": {"sigma_pa": -1.0}}}, "sensors.pressure.sigma_pa"),
        ({"sensors": {"imu": {"pose": {"pitch_deg": 91.0}}}}, "sensors.imu.pose.pitch_deg"),
        ({"sensors": {"sss": {"depression_deg": 61.0}}}, "sensors.sss.depression_deg"),
        ({"sensors": {"lidar": {}}}, "sensors.lidar"),
        ({"trajectory": {"kind": "spiral"}}, "trajectory.kind"),
        ({"trajectory": {"legs": 0}}, "trajectory.legs"),
    ],
)
def test_bad_sensor_fields_are_refused_by_name(data, field):
    with pytest.raises(SpecError) as err:
        parse_spec(data)
    assert any(line.startswith(f"{field}:") or line.startswith(f"{field}.") for line in str(err.value).splitlines())


def test_the_fls_render_grid_follows_its_beams():
    # Three render pixels per min(beam width, beam spacing) at the image centre; the vertical extent covers +-V at
    # the fan's edges.
    w, h, f = FLS().render_size()
    assert (w, h) == (1454, 586) and f == pytest.approx(3 / (3.141592653589793 / 180 * 130 / 256))


def test_the_fls_fan_image_is_bounded_and_counted_in_the_shard_pixels():
    from seasynth.worker.sensors.fan import fan_geometry

    # The default keeps one row per range bin's depth over [0, rmax]: ceil(512 * 40 / 39.5) = 519.
    assert FLS().fan_size() == (943, 519)
    small = FLS(range_m=(0.5, 20.0), beams=64, range_bins=64, horizontal_aperture_deg=60.0)
    assert fan_geometry(small).inside.shape == small.fan_size()[::-1]
    # A thin range window asked one row per bin: 10240 rows and 18563 columns at 9.5-10 m in 512 bins. The default
    # height is now capped, and the fan fills at least 99% of the cap (or reaches the cap on its rows).
    for aperture in (1.0, 60.0, 130.0, 170.0):
        thin = FLS(enabled=True, range_m=(9.5, 10.0), horizontal_aperture_deg=aperture, beams=64, beam_width_deg=0.9)
        w, h = thin.fan_size()
        assert w * h <= MAX_FLS_FAN_PIXELS and (w * h > 0.99 * MAX_FLS_FAN_PIXELS or h == MAX_FLS_FAN_SIDE)
        rw, rh, _ = thin.render_size()
        assert Sensors(fls=thin).render_pixels() == rw * rh + w * h
    # An explicit height whose fan is over the cap is refused by name (4096 rows at 130 deg: 7427 x 4096).
    with pytest.raises(SpecError) as err:
        parse_spec({"sensors": {"fls": {"fan_height_px": 4096}}})
    assert str(err.value).splitlines()[-1].startswith("sensors.fls.fan_height_px: the fan image would be 7427x4096")
    assert FLS(fan_height_px=2000).fan_size() == (3627, 2000)
