"""A three-class dataset with label filters through the whole service (real Redis, Celery workers, the S3 server):
its fetched KITTI tree (semantic/ included) is byte for byte what a local `seasynth generate` writes, and its COCO
and YOLO parts merged by `seasynth fetch --format` are what `seasynth export` makes of that tree."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from service_stack import Stack, tiny_spec, wait_state
from test_service_e2e import local_generate, post, tree

from seasynth.service.fetch import fetch_dataset
from seasynth.worker.export import plan_export, run_export
from seasynth.worker.export.files import EXPORT_RECORD

pytest.importorskip("pycocotools")

# Three classes, one per placement, with a filter that makes some targets DontCare regions.
SPEC = tiny_spec(
    frames=4, shard_size=2, camera={"width": 64, "height": 48},
    targets=[
        {"class_name": "Urchin", "assets": [{"procedural": "urchin", "variants": 1}], "count": [1, 3],
         "scale": [2.0, 3.0]},
        {"class_name": "Debris", "assets": [{"procedural": "rock", "variants": 1}], "count": [1, 2],
         "scale": [3.0, 4.0], "placement": "buried"},
        {"class_name": "Fish", "assets": [{"procedural": "clam", "variants": 1}], "count": [1, 2],
         "scale": [2.0, 3.0], "placement": {"kind": "water", "school": {"size": [1, 2]}}},
    ],
    labels={"min_visible_px": 6},
    outputs={"semantic": True, "coco": True, "yolo": True, "split": [0.5, 0.5, 0.0]},
)


@pytest.fixture(scope="module")
def fetched(stack: Stack, tmp_path_factory) -> tuple[str, Path]:
    import httpx

    with httpx.Client(base_url=stack.api_url, timeout=60) as client:
        dataset_id = post(client, SPEC)
        assert wait_state(client, dataset_id, {"succeeded", "failed"}, timeout=180)["state"] == "succeeded"
    out = tmp_path_factory.mktemp("fetched") / "ds"
    fetch_dataset(stack.api_url, dataset_id, out, progress=False)
    return dataset_id, out


def test_a_three_class_dataset_from_the_service_is_what_generate_writes(fetched, tmp_path):
    _, out = fetched
    got = tree(out)
    local = local_generate(SPEC, tmp_path / "local")
    assert got == {p: data for p, data in local.items() if not p.startswith("export/")}  # its exports: below
    assert {p.split("/")[0] for p in got} == {"image_2", "label_2", "calib", "meta", "semantic"}
    types = {line.split()[0] for p, data in got.items() if p.startswith("label_2/")
             for line in data.decode().splitlines()}
    assert types <= {"Urchin", "Debris", "Fish", "DontCare"} and len(types) >= 2


@pytest.mark.parametrize("fmt", ["coco", "yolo"])
def test_fetched_parts_are_what_export_makes_of_the_fetched_tree(stack, fetched, tmp_path, fmt):
    dataset_id, kitti = fetched
    local = tmp_path / "local"
    run_export(plan_export(kitti, fmt), local)
    out = tmp_path / "parts"
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "fetch", dataset_id, "--out", str(out), "--format", fmt,
                        "--api", stack.api_url], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    got, want = tree(out), tree(local)
    assert json.loads(got.pop(EXPORT_RECORD))["categories"] == ["Urchin", "Debris", "Fish"]
    want.pop(EXPORT_RECORD)
    if fmt == "yolo":
        a, b = yaml.safe_load(got.pop("data.yaml")), yaml.safe_load(want.pop("data.yaml"))
        assert a["names"] == b["names"] == {0: "Urchin", 1: "Debris", 2: "Fish"}
    assert got == want
