"""Sensors on the vehicle keep the camera's clearance: a random pose is drawn again, a survey frame refused."""

from __future__ import annotations

import numpy as np
import pytest

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.scene.sample import CAMERA_CLEARANCE_M, SceneError
from seasynth.worker.sensors import world_from_sensor

EXAMPLE = "examples/urchins.yaml"
FRAMES = range(16)
DVL_BELOW = {"sensors.dvl.enabled": True, "sensors.dvl.pose.offset_m": [0.0, 1.0, 0.0]}  # 1 m along the camera's +y


@pytest.fixture(scope="module")
def session():
    return RenderSession()  # not entered: no GL context, only the asset and terrain sources


def clearance(scene, spec, name: str) -> float:
    """Metres by which the sensor's world position clears the terrain below it, less the camera's margin."""
    p = world_from_sensor(scene.world_from_cam, getattr(spec.sensors, name).pose)[:3, 3]
    return float(p[2] - scene.terrain.height_at(p[None, :2])[0]) - CAMERA_CLEARANCE_M - spec.camera.clip[0]


def test_random_poses_are_drawn_again_until_every_sensor_is_clear(session):
    # The camera looks ~30 deg down from 0.6-1.4 m: a DVL 1 m along its +y (down and forward) would often sit
    # under the seabed. Every frame's DVL now clears it as the camera must; frames whose first clear camera left
    # the DVL inside drew again (further draws, another pose).
    spec = load_spec(EXAMPLE, DVL_BELOW)
    bare = load_spec(EXAMPLE)
    redrawn = 0
    for i in FRAMES:
        scene, plain = session.scene(spec, i), session.scene(bare, i)
        assert clearance(scene, spec, "dvl") >= 0
        if clearance(plain, spec, "dvl") < 0:
            assert scene.camera_tries > plain.camera_tries
            redrawn += 1
        else:
            assert np.array_equal(scene.world_from_cam, plain.world_from_cam)
    assert redrawn >= 3


def test_a_sensor_at_the_vehicle_origin_changes_no_draw(session):
    spec = load_spec(EXAMPLE, {"sensors.dvl.enabled": True, "sensors.fls.enabled": True})
    bare = load_spec(EXAMPLE)
    for i in FRAMES:
        a, b = session.scene(spec, i), session.scene(bare, i)
        assert a.camera_tries == b.camera_tries and np.array_equal(a.world_from_cam, b.world_from_cam)


SURVEY = {"trajectory.kind": "lawnmower", "trajectory.altitude_m": 0.6, "trajectory.pitch_deg": 0.0,
          "trajectory.start_m": [-2.0, -2.0], "trajectory.legs": 1, "trajectory.leg_length_m": 4.0}


def test_a_survey_frame_with_a_sensor_inside_the_seabed_is_refused_by_name(session):
    # Level flight 0.6 m up: the vehicle is clear, a DVL 1 m below it (+y is down when level) is not.
    with pytest.raises(SceneError, match=r"^sensors\.dvl\.pose\.offset_m: at frame 0 the dvl sits at "):
        session.scene(load_spec(EXAMPLE, {**SURVEY, **DVL_BELOW}), 0)
    for ok in ({**DVL_BELOW, "sensors.dvl.enabled": False}, {**DVL_BELOW, "sensors.dvl.pose.offset_m": [0, -1.0, 0]}):
        spec = load_spec(EXAMPLE, {**SURVEY, **ok})
        assert session.scene(spec, 0).world_from_cam[2, 3] == pytest.approx(0.6)
