"""The whole service over HTTP with real Redis, Celery workers and the S3 server: datasets complete exactly once,
their shards assemble into the tree a local generate writes, and failures, kills and cancels behave."""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import httpx
import pytest
from service_stack import Stack, log_since, log_size, tiny_spec, wait_for, wait_state, wait_worker_ready

from seasynth.service import __version__
from seasynth.service.fetch import STATE_DIR, fetch_dataset
from seasynth.service.queues import shard_queue

LOCAL_ONLY = {"seasynth.json", "manifest.json"}  # records beside the frames, not frame files


def tree(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name not in LOCAL_ONLY and STATE_DIR not in p.parts
    }


def local_generate(spec: dict, out: Path) -> dict[str, bytes]:
    """The reference: `seasynth generate` of the same spec on this machine."""
    spec_file = out.with_suffix(".json")
    spec_file.write_text(json.dumps(spec))
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "generate", str(spec_file), "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return tree(out)


def post(client: httpx.Client, spec: dict) -> str:
    r = client.post("/datasets", json=spec)
    assert r.status_code == 202, r.text
    return r.json()["id"]


def shard_members(services, manifest: dict) -> list[tuple[int, dict[str, bytes]]]:
    out = []
    for s in manifest["shards"]:
        data = services.store.get_bytes(s["key"])
        assert hashlib.sha256(data).hexdigest() == s["sha256"] and len(data) == s["bytes"]
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            out.append((s["first_frame"], {m.name: tar.extractfile(m).read() for m in tar}))
    return out


def commits_in(log: str, dataset_id: str) -> int:
    """How many shards of `dataset_id` a worker's log says it committed (seasynth.worker.queue.shard logs one line per commit;
    other tests' datasets may still be committing in the same workers)."""
    return len(re.findall(rf"dataset {dataset_id} shard \d+ committed:", log))


@pytest.mark.parametrize("shard_size, extra_workers", [(2, 0), (4, 1)])
def test_dataset_complete_and_identical_to_local_generate(
    stack: Stack, client, services, tmp_path, shard_size, extra_workers
):
    extra = [stack.start_worker(2) for _ in range(extra_workers)]  # 2 or 3 workers, 2 or 4 processes
    try:
        for w in extra:
            wait_worker_ready(w, 2)
        workers = stack.workers()
        assert len(workers) == 2 + extra_workers
        # Messages earlier tests left (a cancelled dataset's shards) would keep some worker busy meanwhile.
        queue = shard_queue(__version__)
        wait_for(lambda: services.raw_redis.llen(queue) == 0 and services.raw_redis.hlen("unacked") == 0, 120,
                 "the shard queue drained of earlier tests' messages")
        offsets = {w.log: log_size(w) for w in workers}
        spec = tiny_spec(frames=7, shard_size=shard_size)
        dataset_id = post(client, spec)
        seen = set()
        final = wait_state(client, dataset_id, {"succeeded", "failed"})
        # Which worker committed which shard: the records name renderers, not nodes, so read each one's log.
        committed = {w.log: commits_in(log_since(w, offsets[w.log]), dataset_id) for w in workers}
    finally:
        for w in extra:
            w.stop()
    assert final["state"] == "succeeded", final
    n_shards = -(-7 // shard_size)
    assert (final["frames_done"], final["frames_total"]) == (7, 7)
    assert (final["shards_done"], final["shards_failed"], final["shards_total"]) == (n_shards, 0, n_shards)
    assert final["attempts"] == n_shards and final["errors"] == []
    assert final["renderer"] and final["code_version"]
    assert sum(committed.values()) == n_shards, committed
    assert sum(1 for n in committed.values() if n) >= 2, f"one worker rendered every shard: {committed}"

    man = client.get(f"/datasets/{dataset_id}/manifest").json()
    assert man["complete"] and man["seed"] == 7 and man["code_version"] == final["code_version"]
    assert [(s["first_frame"], s["frame_count"]) for s in man["shards"]] == [
        (i, min(shard_size, 7 - i)) for i in range(0, 7, shard_size)
    ]
    assert all(s["key"].startswith(f"datasets/{dataset_id}/shards/") for s in man["shards"])
    stored = json.loads(services.store.get_bytes(f"datasets/{dataset_id}/shards/manifest.json"))
    assert [s["sha256"] for s in stored["shards"]] == [s["sha256"] for s in man["shards"]]

    # Members are the relative paths a local generate writes, with global frame numbers, each exactly once.
    for first, members in shard_members(services, man):
        frames = {int(Path(n).stem) for n in members}
        assert frames == set(range(first, first + len(frames)))
        for n in members:
            assert n.split("/")[0] in {"image_2", "label_2", "calib", "meta"} and n not in seen
            seen.add(n)

    fetched = tmp_path / "fetched"
    report = fetch_dataset(stack.api_url, dataset_id, fetched, progress=False)
    assert (report.shards_total, report.shards_fetched) == (n_shards, n_shards)
    got = tree(fetched)
    assert len(got) == 7 * 4 and set(got) == seen
    assert got == local_generate(spec, tmp_path / "local")

    # A second fetch resumes: nothing downloaded again, the tree unchanged.
    again = fetch_dataset(stack.api_url, dataset_id, fetched, progress=False)
    assert (again.shards_fetched, again.shards_skipped) == (0, n_shards)
    assert tree(fetched) == got


def test_fetch_resumes_a_partial_download_and_rejects_a_corrupt_one(stack: Stack, client, tmp_path):
    dataset_id = post(client, tiny_spec(frames=4, shard_size=2))
    assert wait_state(client, dataset_id, {"succeeded", "failed"})["state"] == "succeeded"
    man = client.get(f"/datasets/{dataset_id}/manifest").json()
    out = tmp_path / "out"
    (out / STATE_DIR).mkdir(parents=True)
    first, second = man["shards"]
    # A download cut in half: the rest comes with a Range request.
    half = httpx.get(first["url"]).content[: first["bytes"] // 2]
    (out / STATE_DIR / (Path(first["key"]).name + ".part")).write_bytes(half)
    # A corrupt partial file: detected by sha256 and downloaded again.
    (out / STATE_DIR / (Path(second["key"]).name + ".part")).write_bytes(b"x" * 10)
    report = fetch_dataset(stack.api_url, dataset_id, out, progress=False)
    assert report.shards_fetched == 2 and len(tree(out)) == 16
    assert not list((out / STATE_DIR).glob("*.part"))
    # The command does the same, with the API address from the environment.
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "fetch", dataset_id, "--out", str(tmp_path / "cli")],
                       capture_output=True, text=True, timeout=120, env={**stack.env, "SEASYNTH_API_URL": stack.api_url})
    assert r.returncode == 0, r.stderr
    assert tree(tmp_path / "cli") == tree(out)


@pytest.mark.parametrize("image_format", ["png", "jpeg"])
def test_single_frame_equals_the_file_in_its_shard(stack: Stack, client, services, tmp_path, image_format):
    jpeg = image_format == "jpeg"
    spec = tiny_spec(frames=5, shard_size=3, **({"outputs": {"image_format": "jpeg", "jpeg_quality": 90}} if jpeg
                                                else {}))
    dataset_id = post(client, spec)
    assert wait_state(client, dataset_id, {"succeeded", "failed"})["state"] == "succeeded"
    man = client.get(f"/datasets/{dataset_id}/manifest").json()
    members = dict(kv for _, m in shard_members(services, man) for kv in m.items())
    image = "image_2/000004.jpg" if jpeg else "image_2/000004.png"
    for index, part, name in [(4, "image", image), (1, "label", "label_2/000001.txt"),
                              (3, "calib", "calib/000003.txt"), (0, "meta", "meta/000000.json")]:
        r = client.get(f"/datasets/{dataset_id}/frames/{index}", params={"part": part})
        assert r.status_code == 200, r.text
        assert r.content == members[name], name
    assert members[image][:3] == (b"\xff\xd8\xff" if jpeg else b"\x89PN")
    assert client.get(f"/datasets/{dataset_id}/frames/2").headers["content-type"] == (
        "image/jpeg" if jpeg else "image/png")
    if jpeg:  # JPEG bytes too are the same through the service as from a local generate
        fetched = tmp_path / "fetched"
        fetch_dataset(stack.api_url, dataset_id, fetched, progress=False)
        assert tree(fetched) == local_generate(spec, tmp_path / "local")
        # The service's preview sheet reads the JPEG images from the shards: the sheet `seasynth preview` draws
        import numpy as np
        from PIL import Image

        from seasynth.worker.preview.sheet import make_preview

        r = client.get(f"/datasets/{dataset_id}/preview.png", params={"frames": 12})
        assert r.status_code == 200, r.text
        local = make_preview(fetched, tmp_path / "sheet.png", frames=12)
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(r.content))), np.asarray(Image.open(local.sheet)))
    assert client.get(f"/datasets/{dataset_id}/frames/5").status_code == 404
    assert client.get(f"/datasets/{dataset_id}/frames/0", params={"part": "depth"}).status_code == 404


PHYSICAL_WATER = {"model": "physical", "jerlov": ["II", "1C"], "depth_m": [6.0, 15.0]}
TWO_LAMPS = [{"offset_m": [x, 0.1, 0.0], "direction": [-x / 2, 0.35, 1.0], "beam_width_deg": 20, "cutoff_deg": 40,
              "intensity": [2.5, 4.0]} for x in (-0.4, 0.4)]


@pytest.mark.parametrize("lamps", [False, True], ids=["sun", "lamps"])
def test_physical_light_datasets_equal_local_generate_frame_for_frame(stack: Stack, client, services, tmp_path,
                                                                     lamps):
    """The physical model through the service, lit by the sun through the water column or by two lamps on the
    vehicle (per-sample shading, shadow maps): the fetched dataset is byte for byte a local generate, and a frame
    served alone is its file in the shard."""
    lighting = {"sun_intensity": [0.0, 0.0], "ambient": [0.0, 0.0], "lamps": TWO_LAMPS} if lamps else {}
    spec = tiny_spec(frames=4, shard_size=2, quality="default", water=PHYSICAL_WATER,
                     **({"lighting": lighting} if lamps else {}))
    dataset_id = post(client, spec)
    final = wait_state(client, dataset_id, {"succeeded", "failed"})
    assert final["state"] == "succeeded", final
    fetched = tmp_path / "fetched"
    fetch_dataset(stack.api_url, dataset_id, fetched, progress=False)
    got = tree(fetched)
    assert len(got) == 4 * 4 and got == local_generate(spec, tmp_path / "local")
    meta = json.loads(got["meta/000003.json"])
    assert meta["water"]["model"] == "physical"
    assert ("lamp0" in meta["water"]["terms"]) == lamps and ("sun" in meta["water"]["terms"]) != lamps
    r = client.get(f"/datasets/{dataset_id}/frames/3", params={"part": "image"})
    assert r.status_code == 200 and r.content == got["image_2/000003.png"]


def test_killed_pool_process_reruns_its_shard_exactly_once(stack: Stack, client, services, tmp_path):
    # Larger frames so a shard renders for long enough to be caught mid-way.
    spec = tiny_spec(frames=6, shard_size=3, quality="high", camera={"width": 160, "height": 120},
                     terrain={"cells": 96, "variants": 1})
    dataset_id = post(client, spec)

    def rendering():
        running = services.records.running(dataset_id)
        return next(iter(running.items()), None)

    shard, who = wait_for(rendering, 60, "a shard to start rendering", interval=0.002)
    os.kill(who["pid"], signal.SIGKILL)
    final = wait_state(client, dataset_id, {"succeeded", "failed"}, timeout=120)
    assert final["state"] == "succeeded", final
    tries = services.records.tries(dataset_id)
    # One shard ran twice: the killed attempt and its rerun (the killed process may have moved on from `shard`
    # to the dataset's other shard between our read and the kill).
    assert sorted(tries.values()) == [1, 2], (shard, tries)
    assert final["attempts"] == sum(tries.values()) == 3
    assert final["frames_done"] == 6 and final["shards_done"] == 2
    man = client.get(f"/datasets/{dataset_id}/manifest").json()
    names = [n for _, m in shard_members(services, man) for n in m]
    assert len(names) == len(set(names)) == 6 * 4
    fetched = tmp_path / "fetched"
    fetch_dataset(stack.api_url, dataset_id, fetched, progress=False)
    assert tree(fetched) == local_generate(spec, tmp_path / "local")


def test_cancel_stops_pending_shards_and_keeps_the_record(stack: Stack, client, services):
    dataset_id = post(client, tiny_spec(frames=200, shard_size=1))
    wait_for(lambda: services.records.get(dataset_id).shards_done >= 1, 60, "a first shard")
    r = client.post(f"/datasets/{dataset_id}/cancel")
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    then = services.records.get(dataset_id)
    processes = sum(1 for _ in stack.workers())  # the session's workers run one process each
    # The shards running at the cancel end (a cancelled shard stops between frames); nothing starts after.
    wait_for(lambda: services.records.running(dataset_id) == {}, 30, "the shards in flight to end")
    settled = services.records.get(dataset_id)
    tries = services.records.tries(dataset_id)
    time.sleep(2)  # the queued shard tasks drain without rendering
    rec = client.get(f"/datasets/{dataset_id}").json()
    assert rec["state"] == "cancelled"
    assert rec["attempts"] == settled.attempts <= then.attempts + processes, "attempts went on after the cancel"
    assert services.records.tries(dataset_id) == tries
    assert rec["shards_done"] == settled.shards_done <= then.shards_done + processes
    assert rec["shards_done"] < 200
    man = client.get(f"/datasets/{dataset_id}/manifest").json()
    assert not man["complete"] and len(man["shards"]) == rec["shards_done"]
    assert not list(services.store.list(f"datasets/{dataset_id}/shards/manifest.json"))
    assert client.post(f"/datasets/{dataset_id}/cancel").status_code == 200  # cancelling again is harmless


def test_purge_deletes_the_objects(stack: Stack, client, services):
    dataset_id = post(client, tiny_spec(frames=4, shard_size=2))
    assert wait_state(client, dataset_id, {"succeeded"})["state"] == "succeeded"
    assert len(list(services.store.list(f"datasets/{dataset_id}/"))) == 5  # 2 shards, 2 markers, manifest
    assert client.post(f"/datasets/{dataset_id}/cancel").status_code == 409  # finished: nothing to cancel
    r = client.delete(f"/datasets/{dataset_id}")
    assert r.status_code == 204, r.text
    assert list(services.store.list(f"datasets/{dataset_id}/")) == []
    assert client.get(f"/datasets/{dataset_id}/manifest").status_code == 404
    assert client.get(f"/datasets/{dataset_id}").status_code == 404
    assert dataset_id not in [d["id"] for d in client.get("/datasets", params={"limit": 100}).json()["items"]]


def test_unusable_asset_fails_the_dataset_after_n_attempts(stack: Stack, client, services):
    data = b"this is not a mesh\n"
    up = client.post("/assets", files={"file": ("broken.obj", data)})
    assert up.status_code == 422, up.text
    assert up.json()["errors"] == ["broken.obj: the obj mesh has no triangles"]
    # One stored before uploads were checked (or that only a worker's loader refuses) still fails cleanly.
    asset_id = hashlib.sha256(data).hexdigest()
    info = {"filename": "broken.obj", "bytes": len(data), "sha256": asset_id}
    services.store.put_bytes(f"assets/{asset_id}.json", json.dumps(info).encode())
    services.store.put_bytes(f"assets/{asset_id}", data)
    spec = tiny_spec(frames=2, shard_size=2, targets={"count": [1, 1], "assets": [{"asset_id": asset_id}]})
    dataset_id = post(client, spec)
    final = wait_state(client, dataset_id, {"succeeded", "failed"}, timeout=60)
    assert final["state"] == "failed"
    assert (final["shards_failed"], final["frames_done"], final["attempts"]) == (1, 0, 3)
    assert final["errors"][0]["shard"] == 0 and "attempt 3" in final["errors"][0]["error"]


def test_uploaded_asset_renders(stack: Stack, client, tmp_path):
    import trimesh

    data = trimesh.creation.box(extents=(0.3, 0.3, 0.3)).export(file_type="ply")
    asset_id = client.post("/assets", files={"file": ("box.ply", data)}).json()["asset_id"]
    spec = tiny_spec(frames=2, shard_size=1, targets={"count": [1, 1], "assets": [{"asset_id": asset_id}]})
    final = wait_state(client, post(client, spec), {"succeeded", "failed"})
    assert final["state"] == "succeeded", final


def test_status_survives_an_api_restart(stack: Stack, client):
    done = post(client, tiny_spec(frames=2, shard_size=2))
    before = wait_state(client, done, {"succeeded"})
    running = post(client, tiny_spec(frames=40, shard_size=1))
    old_url, old = stack.api_url, stack.api_proc
    old.stop()  # SIGTERM: uvicorn's graceful shutdown
    assert old.popen.returncode is not None
    with pytest.raises(httpx.TransportError):
        httpx.get(f"{old_url}/healthz", timeout=2)
    # The session's API from here on is a new process on a new port; the workers never noticed.
    stack.api_proc, stack.api_url = stack.start_api()
    assert stack.api_url != old_url and stack.api_proc.popen.pid != old.popen.pid
    with httpx.Client(base_url=stack.api_url, timeout=60) as new:
        r = new.get(f"/datasets/{done}")
        assert r.status_code == 200 and r.json() == before
        final = wait_state(new, running, {"succeeded", "failed"}, timeout=120)
        assert final["state"] == "succeeded" and final["frames_done"] == 40, final
        listed = new.get("/datasets", params={"limit": 100}).json()
        ids = [d["id"] for d in listed["items"]]
        assert ids.index(running) < ids.index(done)
        created = [d["created_at"] for d in listed["items"]]
        assert created == sorted(created, reverse=True)
