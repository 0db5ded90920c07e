"""Sonar and navigation sensors through the service (real Redis, S3 server, API and Celery workers): a survey with an
FLS, an SSS, a DVL and a pressure sensor fetches byte-identical to a local generate, the single-frame API serves each
sensor file as it is in the shard, and the sensors' renders count in the shard limits as the camera's pixels do."""

from __future__ import annotations

import httpx
import pytest
from service_stack import Stack, tiny_spec, wait_state
from test_admission import unserved_api
from test_service_e2e import local_generate, post, tree

from seasynth.service.fetch import fetch_dataset
from seasynth.service.shards import FRAME_PARTS, frame_file, spec_shard_seconds
from seasynth.service.spec.dataset import MAX_SHARD_MEGAPIXELS, parse_spec

SONAR_PARTS = ("fls", "fls_fan", "fls_label", "sss", "sss_label", "nav")
SENSORS = {
    "fls": {"enabled": True, "beams": 16, "range_bins": 24, "horizontal_aperture_deg": 60.0, "beam_width_deg": 4.0,
            "range_m": [0.5, 6.0], "pose": {"pitch_deg": -15.0}, "noise_sigma": 0.01},
    "sss": {"enabled": True, "range_bins": 16, "range_m": 6.0, "horizontal_beam_deg": 2.0},
    "dvl": {"enabled": True, "pose": {"pitch_deg": -30.0}},
    "pressure": {"enabled": True},
}
# Five frames over a turn (0.25 m per frame, legs of 0.6 m), in shards of two.
SURVEY = tiny_spec(frames=5, shard_size=2, trajectory={"kind": "lawnmower", "leg_length_m": 0.6}, sensors=SENSORS)


@pytest.fixture(scope="module")
def survey(stack: Stack, tmp_path_factory):
    with httpx.Client(base_url=stack.api_url, timeout=60) as client:
        dataset_id = post(client, SURVEY)
        final = wait_state(client, dataset_id, {"succeeded", "failed"}, timeout=180)
    assert final["state"] == "succeeded", final
    fetched = tmp_path_factory.mktemp("sonar") / "fetched"
    report = fetch_dataset(stack.api_url, dataset_id, fetched, progress=False)
    assert (report.shards_total, report.shards_fetched) == (3, 3)
    return dataset_id, tree(fetched)


def test_a_sonar_survey_fetches_byte_identical_to_a_local_generate(survey, tmp_path):
    _, got = survey
    per_frame = ("image_2", "label_2", "calib", "meta", "fls", "fls_fan", "fls_label", "sss", "sss_label", "nav")
    assert set(got) == {f"{d}/{i:06d}{FRAME_PARTS[p][1]}" for i in range(5)
                        for d, p in zip(per_frame, ("image", "label", "calib", "meta", *SONAR_PARTS))}
    assert got == local_generate(SURVEY, tmp_path / "local")


def test_the_frame_api_serves_each_sensor_file_as_in_the_shard(survey, client):
    dataset_id, got = survey
    media = {".png": "image/png", ".json": "application/json"}
    for index in (0, 3):  # the first frame, and one of the second shard past the turn
        for part in SONAR_PARTS:
            r = client.get(f"/datasets/{dataset_id}/frames/{index}", params={"part": part})
            name = frame_file(part, index)
            assert r.status_code == 200, (part, r.text)
            assert r.content == got[name], name
            assert r.headers["content-type"] == media[name[name.rfind("."):]]
            assert r.headers["content-disposition"] == f'inline; filename="{name.replace("/", "_")}"'


def test_a_sensor_part_of_a_dataset_without_that_sensor_is_a_404_naming_the_file(client):
    dataset_id = post(client, tiny_spec(frames=1, shard_size=1))
    r = client.get(f"/datasets/{dataset_id}/frames/0", params={"part": "fls_fan"})
    assert r.status_code == 404, r.text
    assert r.json()["errors"] == [f"frame 0 of dataset {dataset_id} has no fls_fan/000000.png (is that output "
                                  "switched on?)"]
    wait_state(client, dataset_id, {"succeeded", "failed"})


def test_sensors_that_push_a_shard_over_the_time_limit_are_refused_and_the_suggested_size_fits(infra: Stack):
    soft = infra.settings().task_soft_time_limit_s
    camera_only = tiny_spec(frames=400, shard_size=400)
    spec = {**camera_only, "sensors": {"fls": {"enabled": True}}}  # the FLS at its defaults: 1454x586 render and
    # a 943x519 fan image
    cost = lambda s, n=None: spec_shard_seconds(parse_spec(s), n)  # noqa: E731
    assert cost(camera_only) < soft / 2 < soft < cost(spec)
    with unserved_api(infra) as client:
        assert client.post("/datasets", json=camera_only).status_code == 202
        r = client.post("/datasets", json=spec)
        assert r.status_code == 413, r.text
        (line,) = r.json()["errors"]
        head = (f"shard_size: 400 frames of 32x24 at quality 'draft' (up to 4 objects, 16 terrain cells a side, "
                f"{len(parse_spec(spec).terrain.styles)} terrains, 0 of clean/range/depth/instance/coco/yolo/mcap, "
                f"1 sensors rendering {1454 * 586 + 943 * 519} pixels) are estimated at {cost(spec):.0f} s per shard, "
                "over the "
                f"limit of {soft} s (the soft task time limit, SEASYNTH_TASK_TIME_LIMIT_S); use shard_size <= ")
        assert line.startswith(head), line
        fits = int(line[len(head):])
        assert cost(spec, fits) <= soft < cost(spec, fits + 1)
        ok = client.post("/datasets", json={**spec, "shard_size": fits})
        assert ok.status_code == 202, ok.text
        assert ok.json()["shards_total"] == -(-400 // fits)


def test_sensor_render_pixels_count_in_the_megapixel_limit(client: httpx.Client):
    # 1024 beams over 130 deg, 10 deg vertical: a 5810x1132 render (6.6 megapixels) and a 943x519 fan image, a
    # 32x24 camera.
    fls = {"enabled": True, "beams": 1024, "vertical_aperture_deg": 10.0}
    sonar = parse_spec({"sensors": {"fls": fls}}).sensors.fls
    (w, h, _), (fw, fh) = sonar.render_size(), sonar.fan_size()
    px = w * h + fw * fh
    per_shard = 100 * (32 * 24 + px) / 1e6
    assert 100 * 32 * 24 / 1e6 < 1 and per_shard > MAX_SHARD_MEGAPIXELS
    r = client.post("/datasets", json=tiny_spec(frames=100, shard_size=100, sensors={"fls": fls}))
    assert r.status_code == 422, r.text
    assert r.json()["errors"] == [f"(body): shard_size: 100 frames of 32x24 plus {px} sensor render pixels "
                                  f"(sensors.fls, sss, dvl) is {per_shard:.0f} megapixels per shard, over the limit "
                                  f"of {MAX_SHARD_MEGAPIXELS:.0f}; lower shard_size"]


def test_the_frame_api_offers_exactly_the_frame_parts(client):
    params = client.get("/openapi.json").json()["paths"]["/datasets/{id}/frames/{index}"]["get"]["parameters"]
    (part,) = [p for p in params if p["name"] == "part"]
    assert part["schema"]["enum"] == list(FRAME_PARTS) and set(SONAR_PARTS) <= set(FRAME_PARTS)


def test_the_survey_example_runs_through_the_service_as_locally(stack: Stack, tmp_path):
    """examples/survey-sonar.yaml (camera, FLS, SSS, DVL, pressure, IMU on a lawnmower), its first frames at a small
    camera: the service's dataset is the local one, byte for byte."""
    from pathlib import Path

    from seasynth.service.spec.dataset import read_spec_file

    example = read_spec_file(Path(__file__).resolve().parents[2] / "examples" / "survey-sonar.yaml")
    spec = {**example, "frames": 2, "shard_size": 1,
            "camera": {**example["camera"], "width": 64, "height": 48}}
    with httpx.Client(base_url=stack.api_url, timeout=60) as client:
        dataset_id = post(client, spec)
        final = wait_state(client, dataset_id, {"succeeded", "failed"}, timeout=240)
    assert final["state"] == "succeeded", final
    fetch_dataset(stack.api_url, dataset_id, tmp_path / "fetched", progress=False)
    got = tree(tmp_path / "fetched")
    assert {name.split("/")[0] for name in got} >= {"image_2", "fls", "fls_fan", "sss", "nav"}
    assert got == local_generate(spec, tmp_path / "local")
