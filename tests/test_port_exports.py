"""A dataset through a port and a distorting lens, exported: KITTI calib keeps the pinhole P2, meta, COCO image
entries and the MCAP bag's metadata carry the whole camera model, CameraInfo the plumb_bob distortion."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from export_fixtures import FRACTIONS
from local_datasets import generate_variants
from spec_helpers import EXAMPLE
from test_export_mcap import read_bag

from seasynth.service.camera_model import CameraModel
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.export import plan_export, run_export
from seasynth.worker.frame.kitti import parse_calib

CAMERA = {"camera.width": 64, "camera.height": 48, "frames": 3, "outputs.instance": True,
          "camera.port": {"kind": "flat", "thickness_mm": 8.0, "distance_mm": 15.0},
          "camera.distortion": [-0.12, 0.03, 0.001, -0.002, 0.0]}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return generate_variants(tmp_path_factory.mktemp("datasets"), CAMERA, {"port": ({}, 1)})["port"]


def test_meta_coco_and_mcap_carry_the_camera_model_and_calib_the_pinhole(dataset, tmp_path):
    spec = load_spec(EXAMPLE, CAMERA)
    model = CameraModel.from_spec(spec.camera)
    want = json.loads(json.dumps(model.record()))
    for i in range(3):
        meta = json.loads((dataset / "meta" / f"{i:06d}.json").read_text())
        assert meta["camera"]["model"] == want
        P2 = parse_calib((dataset / "calib" / f"{i:06d}.txt").read_text())["P2"]
        np.testing.assert_allclose(P2, np.hstack([model.K, np.zeros((3, 1))]), atol=1e-6)
    run_export(plan_export(dataset, "coco", FRACTIONS), tmp_path / "coco")
    folder = tmp_path / "coco" / "annotations"
    images = [im for split in ("train", "val", "test")
              for im in json.loads((folder / f"instances_{split}.json").read_text())["images"]]
    assert len(images) == 3 and all(im["camera_model"] == want for im in images)
    assert CameraModel.from_record(images[0]["camera_model"]).record() == model.record()
    run_export(plan_export(dataset, "mcap", FRACTIONS), tmp_path / "mcap")
    infos = 0
    for bag in (tmp_path / "mcap").glob("*.mcap"):
        facts, messages = read_bag(bag)
        assert json.loads(facts["metadata"]["seasynth"]["camera_model"]) == want
        for topic, *_, msg in messages:
            if topic == "/camera/camera_info":
                infos += 1
                assert msg.distortion_model == "plumb_bob" and list(msg.d) == list(spec.camera.distortion)
    assert infos == 3
