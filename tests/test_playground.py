"""The playground's renders and its bound on them: previews equal the frames `generate` writes, views and boxes
come from the same frame, the strip scales the camera, and the gate lets each client's newest request render."""

from __future__ import annotations

import asyncio
import base64
import io
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from PIL import Image

from seasynth.api.slots import RenderGate
from seasynth.service.errors import Conflict, Unavailable
from seasynth.service.kitti import parse_label_file
from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.preview.playground import STRIP_WIDTH, preview_reply, preview_spec, render_preview, render_strip

SPEC = {
    "seed": 11,
    "frames": 20,
    "camera": {"width": 64, "height": 48},
    "terrain": {"cells": 16, "variants": 1},
    "targets": {"count": [2, 3], "assets": [{"procedural": "urchin", "variants": 1}]},
    "distractors": {"count": [1, 2], "assets": [{"procedural": "rock", "variants": 1}]},
}


def png_of(data_url: str) -> bytes:
    head, _, b64 = data_url.partition(",")
    assert head == "data:image/png;base64"
    return base64.b64decode(b64)


def pixels(data_url: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png_of(data_url))))


@pytest.fixture(scope="module")
def session():
    with RenderSession() as s:
        yield s


def test_a_preview_is_the_draft_frame_generate_writes_with_its_boxes(session):
    spec = parse_spec(SPEC)  # quality default: the preview renders it at draft all the same
    got = render_preview(session, spec, 5, ["depth", "instance", "clean", "air"])
    draft = parse_spec({**SPEC, "quality": "draft", "outputs": {"depth": True, "instance": True, "clean": True}})
    files = session.frame_files(draft, 5)
    assert png_of(got["images"]["image"]) == files["image_2/000005.png"]
    assert png_of(got["images"]["clean"]) == files["clean/000005.png"]
    labels = parse_label_file(files["label_2/000005.txt"].decode())
    assert got["boxes"] == [{"class": o["type"], "box": o["bbox"], "truncated": o["truncated"],
                             "occluded": o["occluded"]} for o in labels]
    assert len(got["boxes"]) >= 1
    assert (got["frame"], got["seed"], got["width"], got["height"]) == (5, 11, 64, 48)
    # Views line up with the frame: no surface is black in the depth view and dark grey among the instances.
    instance = np.asarray(Image.open(io.BytesIO(files["instance/000005.png"])))
    depth_z = np.asarray(Image.open(io.BytesIO(files["depth/000005.png"])))
    grey = pixels(got["images"]["depth"])
    hit = depth_z > 0
    assert np.array_equal(grey == 0, ~hit)
    # Nearest white, farthest dark grey, and never brighter farther away.
    assert (grey[hit].max(), grey[hit].min()) == (255, 40)
    by_depth = grey[hit][np.argsort(depth_z[hit], kind="stable")]
    assert np.all(np.diff(by_depth.astype(int)) <= 0)
    colours = pixels(got["images"]["instance"])
    for i in np.unique(instance):
        assert len(np.unique(colours[instance == i], axis=0)) == 1  # one colour per instance id
    # In air: the same frame with the water off.
    air = parse_spec({**SPEC, "quality": "draft", "water": {"enabled": False}})
    assert png_of(got["images"]["air"]) == session.frame_files(air, 5)["image_2/000005.png"]
    assert got["images"]["air"] != got["images"]["image"]


def test_only_the_views_asked_for_are_rendered(session):
    got = render_preview(session, parse_spec(SPEC), 0, [])
    assert set(got["images"]) == {"image"}


def test_the_strip_scales_the_camera_and_its_intrinsics(session):
    wide = parse_spec({**SPEC, "camera": {"width": 640, "height": 480,
                                          "intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0}}})
    small = preview_spec(wide, ["image"], width=STRIP_WIDTH, labels=False)
    k = small.camera.intrinsics
    assert (small.camera.width, small.camera.height) == (160, 120)
    assert (k.fx, k.fy, k.cx, k.cy) == (125.0, 125.0, 80.0, 60.0)
    assert small.quality == "draft" and not small.outputs.labels
    strip = render_strip(session, parse_spec(SPEC), 3, 4)
    assert [f["frame"] for f in strip["frames"]] == [3, 4, 5, 6]
    # 64 px cameras are below the strip's width: thumbnails are the draft frames themselves.
    draft = parse_spec({**SPEC, "quality": "draft", "outputs": {"labels": False}})
    for f in strip["frames"]:
        assert png_of(f["image"]) == session.frame_files(draft, f["frame"])[f"image_2/{f['frame']:06d}.png"]


def test_a_worker_reply_names_a_spec_error_as_422_and_answers_json(session):
    header, body = preview_reply(session, "preview", {"camera": {"width": 2}}, [0, []])
    assert header["ok"] is False and header["status"] == 422 and "camera.width" in header["error"]
    assert body == b""
    header, body = preview_reply(session, "strip", SPEC, [0, 2])
    assert header == {"ok": True}
    assert [f["frame"] for f in __import__("json").loads(body)["frames"]] == [0, 1]


def test_a_spec_whose_workspaces_admit_no_scene_is_422_naming_the_workspace(session):
    """Every camera position under the terrain: the spec cannot render (422), not a failed render (500)."""
    buried = {**SPEC, "workspaces": {"camera": {"min": [-5.0, -5.0, -2.0], "max": [5.0, 5.0, -1.0]}}}
    header, body = preview_reply(session, "preview", buried, [0, []])
    assert header["ok"] is False and header["status"] == 422 and body == b""
    assert header["error"].startswith("workspaces.camera: no camera position outside the terrain and objects")


def test_the_gate_renders_each_clients_newest_request_and_says_when_busy():
    async def scenario():
        gate = RenderGate(slots=1, wait_s=0.5)
        release = threading.Event()
        ran: list[str] = []

        def job(name: str, block: bool = False):
            def run():
                if block:
                    release.wait(10)
                ran.append(name)
                return {"name": name}
            return run

        first = asyncio.create_task(gate.run("a", job("a1", block=True)))
        await asyncio.sleep(0.05)  # a1 holds the only slot
        older = asyncio.create_task(gate.run("b", job("b1")))
        await asyncio.sleep(0.01)
        newer = asyncio.create_task(gate.run("b", job("b2")))
        other = asyncio.create_task(gate.run("c", job("c1")))
        gone = asyncio.create_task(gate.run("d", job("d1")))
        await asyncio.sleep(0.01)
        gone.cancel()  # a client that hung up while it waited
        await asyncio.sleep(0.7)  # past wait_s: every waiter gave up
        release.set()
        results = await asyncio.gather(first, older, newer, other, gone, return_exceptions=True)
        return ran, results, dict(gate._latest)

    ran, (a1, b1, b2, c1, d1), left = asyncio.run(scenario())
    assert a1 == {"name": "a1"} and ran == ["a1"]
    assert all(isinstance(r, Unavailable) for r in (b1, b2, c1))
    assert isinstance(d1, asyncio.CancelledError)
    assert left == {}  # no client's entry outlives its request, whichever way it ended

    async def superseded():
        gate = RenderGate(slots=1, wait_s=5)
        release = threading.Event()
        first = asyncio.create_task(gate.run("a", lambda: release.wait(10) and {"n": 1}))
        await asyncio.sleep(0.05)
        older = asyncio.create_task(gate.run("b", lambda: {"n": 2}))
        await asyncio.sleep(0.01)
        newer = asyncio.create_task(gate.run("b", lambda: {"n": 3}))
        await asyncio.sleep(0.05)
        release.set()
        return *await asyncio.gather(first, older, newer, return_exceptions=True), dict(gate._latest)

    first, older, newer, left = asyncio.run(superseded())
    assert first == {"n": 1} and newer == {"n": 3}
    assert isinstance(older, Conflict)
    assert left == {}

    async def one_client_many_slots():
        """Free slots do not let one client render twice at once: its newer request waits for its running one."""
        gate = RenderGate(slots=3, wait_s=5)
        running, peak, order = [0], [0], []

        def job(n: int):
            def run():
                running[0] += 1
                peak[0] = max(peak[0], running[0])
                time.sleep(0.3)
                order.append(n)
                running[0] -= 1
                return n
            return run

        tasks = []
        for n in range(3):
            tasks.append(asyncio.create_task(gate.run("a", job(n))))
            await asyncio.sleep(0.05)
        other = asyncio.create_task(gate.run("b", job(9)))  # another client takes another slot meanwhile
        results = await asyncio.gather(*tasks, other, return_exceptions=True)
        return results, peak[0], order, dict(gate._latest), dict(gate._clients)

    (r0, r1, r2, r9), peak, order, left, clients = asyncio.run(one_client_many_slots())
    assert (r0, r2, r9) == (0, 2, 9) and isinstance(r1, Conflict)
    assert peak == 2 and order.index(0) < order.index(2)  # client a never twice at once; b beside it
    assert left == {} and clients == {}


def test_local_runs_go_one_at_a_time_and_report_their_progress(tmp_path):
    from seasynth.api.playground_local import LocalRuns

    runs = LocalRuns(tmp_path)
    first = runs.start({**SPEC, "frames": 200})
    try:
        assert (first.state, first.frames_total) == ("running", 200)
        assert first.out == str(tmp_path / first.id / "dataset")
        with pytest.raises(Conflict, match=f"local run {first.id} is still running"):
            runs.start(SPEC)
        assert len(list(tmp_path.iterdir())) == 1  # the refused run made no folder
    finally:
        runs.close()
    assert runs.status(first.id).state == "failed"  # terminated, and the dataset says incomplete


def test_a_local_run_reads_relative_files_where_the_previews_do(tmp_path, monkeypatch):
    """A path typed in the page is read from the playground's folder by the previews: the run's spec names it so,
    not relative to the run's own folder."""
    from seasynth.api.playground_local import LocalRuns

    monkeypatch.chdir(tmp_path)
    runs = LocalRuns(tmp_path / "runs")
    run = runs.start({**SPEC, "frames": 1, "targets": {"assets": [{"path": "meshes/ball.obj"}]}})
    try:
        written = yaml.safe_load((tmp_path / "runs" / run.id / "spec.yaml").read_text())
    finally:
        runs.close()
    assert written["targets"]["assets"] == [{"path": str(tmp_path / "meshes" / "ball.obj")}]


def test_the_local_playground_answers_only_its_loopback_host_names():
    """A page of another site whose name resolves to 127.0.0.1 (DNS rebinding) sends its own Host: refused."""
    from seasynth.api.playground_local import create_local_app

    app = create_local_app(None, {}, Path("/nonexistent"))

    async def get(host: str) -> int:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url=f"http://{host}:8765") as c:
            return (await c.get("/playground/config")).status_code

    assert [asyncio.run(get(h)) for h in ("127.0.0.1", "localhost", "evil.example")] == [200, 200, 400]
    shared = create_local_app(None, {}, Path("/nonexistent"), allowed_hosts=None)  # --host 0.0.0.0 on purpose

    async def get_shared() -> int:
        transport = httpx.ASGITransport(app=shared)
        async with httpx.AsyncClient(transport=transport, base_url="http://workstation.lan:8765") as c:
            return (await c.get("/playground/config")).status_code

    assert asyncio.run(get_shared()) == 200


def test_each_procedural_kind_has_a_small_png_thumbnail_and_an_unknown_kind_is_404():
    """The asset picker's thumbnails: every kind the spec takes, a 128x96 PNG under 20 KB, and 404 naming an
    unknown kind; the page's config lists the same kinds."""
    from typing import get_args

    from seasynth.api.playground_local import create_local_app
    from seasynth.service.spec.scene import ProceduralTarget

    app = create_local_app(None, {}, Path("/nonexistent"))

    async def gets(paths: list[str]) -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1:8765") as c:
            return [await c.get(p) for p in paths]

    kinds = list(get_args(ProceduralTarget))
    config, *thumbs, unknown = asyncio.run(gets(["/playground/config"] + [f"/playground/kinds/{k}.png" for k in kinds]
                                                + ["/playground/kinds/kraken.png"]))
    assert config.json()["kinds"] == kinds and len(kinds) == 19
    for kind, r in zip(kinds, thumbs):
        assert r.status_code == 200 and r.headers["content-type"] == "image/png", kind
        assert r.content[:8] == b"\x89PNG\r\n\x1a\n" and len(r.content) < 20_000, kind
        assert Image.open(io.BytesIO(r.content)).size == (128, 96), kind
    assert len({r.content for r in thumbs}) == len(kinds)  # each its own picture
    assert unknown.status_code == 404 and "kraken" in unknown.json()["detail"]
