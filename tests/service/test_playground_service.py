"""The playground served by the API (`seasynth serve`) with SEASYNTH_API_KEYS set: the page loads without a key and
asks for one, previews are rendered by a frames-queue worker byte-identical to the local draft frame, and specs the
service cannot render are refused naming the field."""

from __future__ import annotations

import base64
import sys
from pathlib import Path

import httpx
import pytest
from service_stack import Stack, tiny_spec

from seasynth.service.spec.dataset import parse_spec

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from browser import chromium, set_value, wait  # noqa: E402

KEY = "playground-key"


@pytest.fixture(scope="module")
def keyed(stack: Stack):
    proc, url = stack.start_api({"SEASYNTH_API_KEYS": KEY})
    yield url
    proc.stop()


def local_draft_png(spec: dict, frame: int) -> bytes:
    from seasynth.worker.frame.function import RenderSession

    with RenderSession() as s:
        return s.frame_files(parse_spec({**spec, "quality": "draft"}), frame)[f"image_2/{frame:06d}.png"]


def test_the_page_is_public_and_its_calls_need_the_key(keyed):
    page = httpx.get(f"{keyed}/playground")
    assert page.status_code == 200 and "<title>seasynth playground</title>" in page.text
    for public in ("static/app.js", "static/classes.js", "kinds/urchin.png"):  # an <img> sends no key
        assert httpx.get(f"{keyed}/playground/{public}").status_code == 200, public
    assert httpx.get(f"{keyed}/playground/config").status_code == 401
    r = httpx.post(f"{keyed}/playground/preview", json={"spec": tiny_spec()})
    assert r.status_code == 401
    got = httpx.get(f"{keyed}/playground/config", headers={"X-API-Key": KEY}).json()
    assert got["mode"] == "service" and got["schema"]["title"] == "DatasetSpec"


def test_a_worker_renders_the_preview_as_the_local_draft_frame(keyed):
    spec = tiny_spec()
    r = httpx.post(f"{keyed}/playground/preview", json={"spec": spec, "frame": 3, "views": ["depth"]},
                   headers={"X-API-Key": KEY}, timeout=60)
    assert r.status_code == 200, r.text
    body = r.json()
    assert set(body["images"]) == {"image", "depth"}
    assert base64.b64decode(body["images"]["image"].split(",", 1)[1]) == local_draft_png(spec, 3)
    strip = httpx.post(f"{keyed}/playground/strip", json={"spec": spec, "first": 2, "count": 3},
                       headers={"X-API-Key": KEY}, timeout=60).json()
    assert [f["frame"] for f in strip["frames"]] == [2, 3, 4]


def test_specs_the_service_cannot_render_are_refused_naming_the_field(keyed):
    spec = tiny_spec(terrain={"cells": 16, "variants": 1, "mesh": {"path": "/etc/passwd"}})
    r = httpx.post(f"{keyed}/playground/preview", json={"spec": spec}, headers={"X-API-Key": KEY})
    assert r.status_code == 422
    assert "terrain.mesh.path: local paths and URLs are not accepted here" in r.json()["detail"]
    r = httpx.post(f"{keyed}/playground/preview", json={"spec": tiny_spec(camera={"width": 1})},
                   headers={"X-API-Key": KEY})
    assert r.status_code == 422 and "camera.width" in r.json()["detail"]


def test_in_the_browser_the_page_asks_for_the_key_then_previews(keyed, tmp_path):
    with chromium(tmp_path) as driver:
        driver.get(f"{keyed}/playground")
        box = wait(lambda: (b := driver.find_element("id", "key-box")).is_displayed() and b, 30, "the key prompt")
        assert "API key" in box.text
        set_value(driver, "api-key", KEY)
        wait(lambda: driver.find_elements("id", "f-camera.width"), 30, "the form, once the key is given")
        set_value(driver, "f-camera.width", 64)
        set_value(driver, "f-camera.height", 48)
        spec = wait(lambda: (s := driver.execute_script("return spec;"))["camera"] == {"width": 64, "height": 48}
                    and s, 10, "the page's spec")
        r = httpx.post(f"{keyed}/playground/preview", json={"spec": spec, "frame": 0, "views": []},
                       headers={"X-API-Key": KEY}, timeout=330)  # the default water's columns are solved first
        assert r.status_code == 200, r.text
        want = r.json()["images"]["image"]
        wait(lambda: driver.find_element("id", "preview-image").get_attribute("src") == want, 90,
             "the worker's preview on the page")


def test_in_the_browser_generate_posts_the_dataset_and_follows_it(keyed, tmp_path):
    spec = tiny_spec()
    with chromium(tmp_path) as driver:
        driver.get(f"{keyed}/playground")
        wait(lambda: driver.find_element("id", "key-box").is_displayed(), 30, "the key prompt")
        set_value(driver, "api-key", KEY)
        wait(lambda: driver.find_elements("id", "f-camera.width"), 30, "the form")
        driver.execute_script("spec = arguments[0]; buildForm(); refresh();", spec)  # a spec loaded as a whole
        wait(lambda: {"frames: 6", "seed: 7"} <= set(
            driver.find_element("id", "spec-yaml").get_attribute("value").splitlines()), 30, "the tiny spec's YAML")
        driver.find_element("id", "generate").click()
        text = wait(lambda: (t := driver.find_element("id", "generate-progress").text) and
                    any(s in t for s in ("succeeded", "failed", "error")) and t, 120, "the dataset to finish")
    assert "succeeded, 6/6 frames" in text, text
    dataset_id = text.split(":", 1)[0]
    listed = httpx.get(f"{keyed}/datasets", headers={"X-API-Key": KEY}).json()["items"]
    match = [d for d in listed if d["id"].startswith(dataset_id)]
    assert len(match) == 1 and match[0]["state"] == "succeeded" and match[0]["seed"] == 7


def test_in_the_browser_a_mesh_uploaded_in_the_asset_picker_is_ticked_and_every_picker_shows_it(keyed, tmp_path):
    """The picker's upload: POST /assets with the key, the mesh ticked in that class's assets (by its sha256 id), a
    tile for it in the distractors' picker too, and the worker's preview of the spec with it on the page."""
    import hashlib

    import trimesh

    mesh = tmp_path / "box.ply"
    mesh.write_bytes(trimesh.creation.box(extents=(0.2, 0.2, 0.2)).export(file_type="ply"))
    asset_id = hashlib.sha256(mesh.read_bytes()).hexdigest()
    with chromium(tmp_path) as driver:
        driver.get(f"{keyed}/playground")
        wait(lambda: driver.find_element("id", "key-box").is_displayed(), 30, "the key prompt")
        set_value(driver, "api-key", KEY)
        wait(lambda: driver.find_elements("id", "f-camera.width"), 30, "the form")
        driver.execute_script("spec = arguments[0]; buildForm(); refresh();", tiny_spec())
        driver.find_element("id", "upload-targets.0.assets").send_keys(str(mesh))
        spec = wait(lambda: (s := driver.execute_script("return spec;")) and isinstance(s["targets"], list) and
                    {"asset_id": asset_id} in s["targets"][0]["assets"] and s, 30, "the uploaded mesh in the spec")
        tile = f"pick-{{}}-upload-{asset_id[:12]}"
        assert "picked" in driver.find_element("id", tile.format("targets.0.assets")).get_attribute("class")
        assert "picked" not in driver.find_element("id", tile.format("distractors.assets")).get_attribute("class")
        assert driver.find_element("id", tile.format("distractors.assets")).get_attribute("title") == "box.ply"
        want = httpx.post(f"{keyed}/playground/preview", json={"spec": spec, "frame": 0, "views": []},
                          headers={"X-API-Key": KEY}, timeout=60)
        assert want.status_code == 200, want.text
        wait(lambda: driver.find_element("id", "preview-image").get_attribute("src") == want.json()["images"]["image"],
             90, "the worker's preview of the spec with the mesh")
