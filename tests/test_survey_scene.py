"""A survey (trajectory: lawnmower) takes its pose from the trajectory only: it draws no random camera, so a camera
workspace that admits no position neither fails nor changes it; random-pose frames still draw theirs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from local_datasets import tree

from seasynth.service.seeds import frame_rng
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.local.generate import generate
from seasynth.worker.scene.sample import SceneError, sample_scene
from seasynth.worker.scene.trajectory import lawnmower_state

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
SURVEY = {"camera.width": 32, "camera.height": 24, "frames": 3, "shard_size": 3, "trajectory.kind": "lawnmower",
          "sensors.pressure.enabled": True}
# Entirely below the seabed (terrain relief is well under 1 m): every random camera position is inside the terrain.
BURIED = {"workspaces.camera.min": [-1.0, -1.0, -6.0], "workspaces.camera.max": [1.0, 1.0, -5.0]}


def test_a_random_pose_spec_with_a_buried_camera_workspace_is_refused_naming_the_workspace():
    spec = load_spec(EXAMPLE, {"camera.width": 32, "camera.height": 24, **BURIED})
    with RenderSession() as session, pytest.raises(SceneError, match=r"^workspaces\.camera: no camera position"):
        sample_scene(spec, frame_rng(spec.seed, 0), session.asset_for, session.terrain_for)


def test_a_survey_draws_no_camera_and_ignores_the_camera_workspace(tmp_path):
    spec = load_spec(EXAMPLE, SURVEY)
    with RenderSession() as session:
        scene = sample_scene(spec, frame_rng(spec.seed, 0), session.asset_for, session.terrain_for)
    T = lawnmower_state(spec.trajectory, 0).world_from_vehicle
    assert np.array_equal(scene.world_from_cam, T) and scene.camera_tries == 0 and scene.look_at_instance is None
    generate(spec, tmp_path / "survey", workers=1)
    generate(load_spec(EXAMPLE, {**SURVEY, **BURIED}), tmp_path / "buried", workers=1)
    a, b = tree(tmp_path / "survey"), tree(tmp_path / "buried")
    a.pop("seasynth.json"), b.pop("seasynth.json")  # the dataset records hold the two specs
    assert a == b and len(a) == 3 * 5  # image, label, calib, meta, nav of 3 frames, byte for byte
