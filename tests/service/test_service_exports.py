"""Generate-time export formats and the preview sheet through the whole service (real Redis, Celery workers, the S3
server): each shard's parts are in the bucket and the manifest, `seasynth fetch --format` merges them into exactly
what `seasynth export` makes of the fetched KITTI tree, a re-rendered shard uploads the same part bytes, and
GET /datasets/{id}/preview.png draws the sheet `seasynth preview` draws."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from isolated_stacks import api_on
from PIL import Image
from service_stack import Stack, tiny_spec, wait_for, wait_state
from test_admission import unserved_api

from seasynth.service import __version__
from seasynth.service.fetch import STATE_DIR, fetch_dataset
from seasynth.service.queues import TASK_SHARD, shard_queue
from seasynth.service.records.types import ShardCommit
from seasynth.service.shards import commit_key, export_part_key, shard_key
from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.export import SPLITS, plan_export, run_export
from seasynth.worker.export.files import EXPORT_RECORD
from seasynth.worker.export.merge import PartMerger, mcap_name
from seasynth.worker.frame.function import frame_paths
from seasynth.worker.preview.sheet import make_preview

pytest.importorskip("pycocotools")
from pycocotools.coco import COCO  # noqa: E402

FORMATS = ("coco", "yolo", "mcap")
# 5 frames in shards of 2, 2 and 1; no instance/ output, so COCO's masks come from the frames rendered for it.
SPEC = tiny_spec(frames=5, shard_size=2,
                 outputs={"coco": True, "yolo": True, "mcap": True, "split": [0.5, 0.25, 0.25]})


def tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and STATE_DIR not in p.parts}


def post(client, spec: dict) -> str:
    r = client.post("/datasets", json=spec)
    assert r.status_code == 202, r.text
    return r.json()["id"]


@pytest.fixture(scope="module")
def dataset(stack: Stack, client_module, tmp_path_factory) -> tuple[str, Path]:
    """A finished dataset with every export format, and its KITTI tree fetched."""
    dataset_id = post(client_module, SPEC)
    assert wait_state(client_module, dataset_id, {"succeeded", "failed"}, timeout=120)["state"] == "succeeded"
    kitti = tmp_path_factory.mktemp("kitti") / "ds"
    fetch_dataset(stack.api_url, dataset_id, kitti, progress=False)
    return dataset_id, kitti


@pytest.fixture(scope="module")
def client_module(stack: Stack):
    import httpx

    with httpx.Client(base_url=stack.api_url, timeout=60) as c:
        yield c


def test_every_shard_lists_its_parts_and_keeps_only_the_spec_outputs(dataset, client, services):
    dataset_id, _ = dataset
    man = client.get(f"/datasets/{dataset_id}/manifest").json()
    assert [s["frame_count"] for s in man["shards"]] == [2, 2, 1]
    spec = parse_spec(SPEC)
    for s in man["shards"]:
        assert sorted(s["exports"]) == sorted(FORMATS)
        for fmt, part in s["exports"].items():
            assert part["key"] == export_part_key(dataset_id, s["index"], fmt)
            data = services.store.get_bytes(part["key"])
            assert (hashlib.sha256(data).hexdigest(), len(data)) == (part["sha256"], part["bytes"])
        marker = ShardCommit.from_json(services.store.get_bytes(commit_key(dataset_id, s["index"])))
        assert {p.format: (p.key, p.sha256, p.bytes) for p in marker.exports} == {
            f: (p["key"], p["sha256"], p["bytes"]) for f, p in s["exports"].items()}
        # COCO's masks were rendered for the part, yet the KITTI tar has only what the spec asks for (no instance/).
        with tarfile.open(fileobj=io.BytesIO(services.store.get_bytes(s["key"]))) as tar:
            names = [m.name for m in tar]
        frames = range(s["first_frame"], s["first_frame"] + s["frame_count"])
        assert names == [p for i in frames for p in sorted(frame_paths(spec, i))]
    stored = json.loads(services.store.get_bytes(f"datasets/{dataset_id}/shards/manifest.json"))
    assert all("url" not in p for s in stored["shards"] for p in s["exports"].values())


@pytest.mark.parametrize("fmt", ["coco", "yolo"])
def test_fetch_format_is_byte_identical_to_exporting_the_fetched_kitti_tree(stack, dataset, tmp_path, fmt):
    """Byte for byte, every file but seasynth-export.json (which says where the export came from) and YOLO's
    data.yaml (whose `path` names its own folder). The local export re-renders COCO's masks from the KITTI files and
    checks the re-rendered images and labels against them byte for byte, so the masks agree too."""
    dataset_id, kitti = dataset
    local = tmp_path / "local"
    run_export(plan_export(kitti, fmt), local)  # the spec's outputs.split
    out = tmp_path / "fetched"
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "fetch", dataset_id, "--out", str(out), "--format", fmt,
                        "--api", stack.api_url], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    files = len(tree(out))
    assert r.stdout.splitlines()[-1] == f"{out}: 3 {fmt} parts (3 fetched, 0 already complete), {files} files written"
    got, want = tree(out), tree(local)
    record = json.loads(got.pop(EXPORT_RECORD))
    assert record["dataset"]["id"] == dataset_id and record["split"] == {"train": 0.5, "val": 0.25, "test": 0.25}
    assert record["frames"] == json.loads(want.pop(EXPORT_RECORD))["frames"]
    if fmt == "yolo":
        a, b = yaml.safe_load(got.pop("data.yaml")), yaml.safe_load(want.pop("data.yaml"))
        assert (a.pop("path"), b.pop("path")) == (str(out), str(local)) and a == b
    assert got == want
    if fmt == "coco":
        ids = []
        for split in SPLITS:
            coco = COCO(str(out / "annotations" / f"instances_{split}.json"))
            ids += list(coco.anns)
            assert sorted(coco.imgs) == sorted(int(p.stem) for p in (out / "images" / split).iterdir())
        assert len(ids) == len(set(ids)) > 0  # annotation ids are unique across shards and splits
    # Again into the same folder: nothing is downloaded, the same files are there.
    again = fetch_dataset(stack.api_url, dataset_id, out, progress=False, merger=PartMerger(fmt))
    assert (again.shards_fetched, again.shards_skipped) == (0, 3)
    assert tree(out).keys() == {*got, EXPORT_RECORD, *(["data.yaml"] if fmt == "yolo" else [])}


def test_fetch_format_mcap_puts_each_shard_bag_in_one_folder(stack, dataset, tmp_path):
    """One bag per shard and split, whose messages together are the local export's bag of that split."""
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    def messages(paths: list[Path]) -> list[tuple]:
        out = []
        for path in paths:
            with open(path, "rb") as f:
                out += [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]
        return sorted(out)

    dataset_id, kitti = dataset
    local = tmp_path / "local"
    run_export(plan_export(kitti, "mcap"), local)
    out = tmp_path / "fetched"
    fetch_dataset(stack.api_url, dataset_id, out, progress=False, merger=PartMerger("mcap"))
    assert sorted(tree(out)) == sorted([EXPORT_RECORD] + [mcap_name(s, i) for s in SPLITS for i in range(3)])
    for split in SPLITS:
        assert messages([out / mcap_name(split, i) for i in range(3)]) == messages([local / f"{split}.mcap"])


def test_a_shard_rendered_again_uploads_identical_parts(stack, dataset, services):
    """Shard 1's tar, parts and marker are lost; the shard task runs again on a worker: every part comes back with
    the same bytes under the same key. A second dataset of the same spec gets the same bytes too."""
    dataset_id, _ = dataset
    keys = [shard_key(dataset_id, 1), *(export_part_key(dataset_id, 1, f) for f in FORMATS)]
    before = {k: services.store.get_bytes(k) for k in keys}
    services.store.delete(commit_key(dataset_id, 1))
    for key in keys:
        services.store.delete(key)
    r, records = services.records._r, services.records
    r.srem(records._key(dataset_id, "done"), 1)  # as if Redis had lost its commit too
    r.hdel(records._key(dataset_id, "shards"), 1)
    r.hincrby(records._key(dataset_id), "frames_done", -2)
    services.producer.send_task(TASK_SHARD, args=[dataset_id, 1], queue=shard_queue(__version__))
    wait_for(lambda: services.store.head(commit_key(dataset_id, 1)), 60, "shard 1 to commit again", interval=0.2)
    assert {k: services.store.get_bytes(k) for k in keys} == before
    assert records.attempts(dataset_id, 1) == 2

    import httpx

    with httpx.Client(base_url=stack.api_url, timeout=60) as client:
        twin = post(client, SPEC)
        assert wait_state(client, twin, {"succeeded", "failed"}, timeout=120)["state"] == "succeeded"
    for i in range(3):
        for fmt in FORMATS:
            assert services.store.get_bytes(export_part_key(twin, i, fmt)) == \
                services.store.get_bytes(export_part_key(dataset_id, i, fmt))


def test_fetch_format_of_a_dataset_without_that_output_is_refused(stack, client, tmp_path):
    plain = post(client, tiny_spec(frames=2, shard_size=2))
    assert wait_state(client, plain, {"succeeded", "failed"})["state"] == "succeeded"
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "fetch", plain, "--out", str(out), "--format", "yolo",
                        "--api", stack.api_url], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert f"dataset {plain} was generated without outputs.yolo" in r.stderr and "seasynth export" in r.stderr
    assert not out.exists()  # refused before anything was written
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "fetch", plain, "--out", str(out), "--format", "voc",
                        "--api", stack.api_url], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Invalid value for '--format'" in r.stderr


@pytest.mark.parametrize("tile_width", [320, 16])
def test_preview_is_the_sheet_of_the_first_shards_and_is_cached(dataset, client, services, tmp_path, tile_width):
    """With frames >= the dataset's, the sheet covers every shard: pixel for pixel the sheet `seasynth preview`
    draws of the fetched KITTI tree (scaled alike at a tile width below the frames' 32 px)."""
    dataset_id, kitti = dataset
    r = client.get(f"/datasets/{dataset_id}/preview.png", params={"frames": 12, "tile_width": tile_width})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    local = make_preview(kitti, tmp_path / "sheet.png", frames=12, tile_width=tile_width)
    assert local.tiles == 5
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(r.content))), np.asarray(Image.open(local.sheet)))
    cached = [o.key for o in services.store.list(f"datasets/{dataset_id}/previews/")]
    key = next(k for k in cached if r.headers["etag"].strip('"') in k)
    assert services.store.get_bytes(key) == r.content
    again = client.get(f"/datasets/{dataset_id}/preview.png", params={"frames": 12, "tile_width": tile_width})
    assert (again.content, again.headers["etag"]) == (r.content, r.headers["etag"])
    # Two frames come from shard 0 alone: another sheet, under another key.
    two = client.get(f"/datasets/{dataset_id}/preview.png", params={"frames": 2, "tile_width": tile_width})
    assert two.status_code == 200 and two.headers["etag"] != r.headers["etag"]


def test_a_preview_too_large_to_draw_is_422_and_one_of_an_unreadable_shard_502(infra):
    """Refused before any shard is read: a sheet over MAX_SHEET_PIXELS (a remote caller could otherwise have the
    API allocate gigabytes); a shard in the bucket that is not a tar is the data's fault behind the API: 502."""
    import time
    import uuid

    from seasynth.api.deps import open_services

    big = tiny_spec(frames=48, shard_size=24)
    big["camera"] = {**big["camera"], "width": 4096, "height": 4096}
    big["outputs"] = {**big.get("outputs", {}), "depth": True, "instance": True}
    spec = parse_spec(big)
    services = open_services(infra.settings(key_prefix="previews"))
    dataset_id = uuid.uuid4().hex
    try:
        services.records.create(dataset_id, spec.model_dump(mode="json"), seed=spec.seed, code_version=__version__,
                                frames=48, shard_size=24, shards=2, now=time.time())
        key = shard_key(dataset_id, 0, "none")
        services.store.put_bytes(key, b"not a tar")
        services.records.commit(dataset_id, ShardCommit(0, key, 0, 24, hashlib.sha256(b"not a tar").hexdigest(), 9,
                                                        __version__, "r"))
        with api_on(services) as c:
            r = c.get(f"/datasets/{dataset_id}/preview.png", params={"frames": 48, "tile_width": 4096})
            assert r.status_code == 422, r.text
            assert r.json()["detail"].startswith("frames, tile_width: a sheet of 48 frames of 4096x4096 (3 panels "
                                                 "each) at tile_width 4096 would be 49172x49348 px, over the 64 Mpx")
            r = c.get(f"/datasets/{dataset_id}/preview.png", params={"frames": 1, "tile_width": 64})
            assert r.status_code == 502 and r.json()["detail"].startswith(f"{key}: unreadable shard tar"), r.text
            responses = c.get("/openapi.json").json()["paths"]["/datasets/{id}/preview.png"]["get"]["responses"]
            assert {"404", "422", "502"} <= set(responses)
        assert list(services.store.list(f"datasets/{dataset_id}/previews/")) == []
    finally:
        services.store.delete(key)
        services.close()


def test_preview_before_any_shard_is_404_and_keys_are_needed(infra, dataset, client):
    with unserved_api(infra) as unserved:
        waiting = post(unserved, tiny_spec(frames=2, shard_size=1))
        r = unserved.get(f"/datasets/{waiting}/preview.png")
        assert r.status_code == 404 and "has no committed shard yet" in r.json()["detail"], r.text
    assert client.get("/datasets/" + "0" * 32 + "/preview.png").status_code == 404
    assert client.get(f"/datasets/{dataset[0]}/preview.png", params={"frames": 0}).status_code == 422
    paths = client.get("/openapi.json").json()["paths"]
    responses = paths["/datasets/{id}/preview.png"]["get"]["responses"]
    assert "image/png" in responses["200"]["content"] and "404" in responses
    from seasynth.api.deps import open_services

    keyed = open_services(infra.settings(api_keys="k1"))
    try:
        with api_on(keyed) as c:
            assert c.get(f"/datasets/{dataset[0]}/preview.png").status_code == 401
            assert c.get(f"/datasets/{dataset[0]}/preview.png", headers={"X-API-Key": "k1"}).status_code == 200
    finally:
        keyed.close()
