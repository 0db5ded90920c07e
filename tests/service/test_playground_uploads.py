"""The playground's asset picker in the service, in a real headless Chromium: every uploaded mesh listed by GET /assets
shows as a tile with its picture beside the procedural kinds (also after a reload, and with an API key, which an
<img> alone would not send); a mesh uploaded from the page shows at once and after a reload; a mesh without a picture
still lists, and images do not (the picker's fields take meshes). A ticked upload is in the spec the worker previews.

With SEASYNTH_SCREENSHOTS=DIR the picker is kept as DIR/playground-uploads.png (docs/playground.md shows it)."""

from __future__ import annotations

import base64
import json
import sys
from pathlib import Path

import httpx
import pytest
import trimesh
from service_stack import Stack

from seasynth.service.shards import asset_thumbnail_key

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from browser import chromium, page_spec, preview_src, server_preview, set_value, shot, wait

KEY = "picker-key"


@pytest.fixture(scope="module")
def keyed(stack: Stack):
    proc, url = stack.start_api({"SEASYNTH_API_KEYS": KEY})
    with httpx.Client(base_url=url, timeout=60, headers={"X-API-Key": KEY}) as c:
        yield c
    proc.stop()


def tile(driver, asset_id: str) -> str:
    return f"pick-targets.0.assets-upload-{asset_id[:12]}"


def picture(driver, asset_id: str) -> dict:
    """The tile's picture as the page shows it: its state, size and (when shown) its PNG bytes."""
    got = driver.execute_async_script("""
        const [id, done] = arguments, img = document.querySelector(`[id='${id}'] .upload-picture`);
        if (!img) return done(null);
        const out = {state: img.dataset.state, w: img.naturalWidth, h: img.naturalHeight, png: null};
        if (img.dataset.state !== "shown" || !img.complete) return done(out);
        fetch(img.src).then((r) => r.arrayBuffer()).then((b) => {
          out.png = btoa(String.fromCharCode(...new Uint8Array(b))); done(out); });""", tile(driver, asset_id))
    if got and got["png"]:
        got["png"] = base64.b64decode(got["png"])
    return got


def every_asset(api) -> list[dict]:
    items, url = [], "/assets?limit=100"
    while url:
        body = api.get(url).json()
        items, url = items + body["items"], body["next"]
    return items


def open_page(driver, url: str) -> None:
    driver.get(f"{url}/playground")
    set_value(driver, "api-key", KEY)
    wait(lambda: driver.find_elements("id", "f-targets.0.assets"), 30, "the form")


def test_uploaded_meshes_show_with_their_pictures_after_a_reload(keyed, services, tmp_path):
    ball = trimesh.creation.icosphere(1, radius=0.3).export(file_type="ply")
    mesh = keyed.post("/assets", files={"file": ("ball.ply", ball)}).json()["asset_id"]
    png = keyed.post("/assets", files={"file": ("sand.png", _png())}).json()["asset_id"]
    bare_mesh = trimesh.creation.cylinder(0.1, 0.8).export(file_type="stl")
    bare = keyed.post("/assets", files={"file": ("pipe.stl", bare_mesh)}).json()["asset_id"]
    services.store.delete(asset_thumbnail_key(bare))  # and none can be drawn of it:
    why = asset_thumbnail_key(bare).removesuffix(".png") + ".json"
    services.store.put_bytes(why, json.dumps({"error": "MemoryError"}).encode())
    upload = tmp_path / "crate.obj"
    upload.write_bytes(trimesh.creation.box((0.5, 0.3, 0.2)).export(file_type="obj").encode())
    url = str(keyed.base_url).rstrip("/")
    with chromium(tmp_path, width=1120, height=1000) as driver:
        open_page(driver, url)
        listed = [i["asset_id"] for i in every_asset(keyed) if i["kind"] == "mesh"]
        tiles = driver.find_elements("css selector", "[id='f-targets.0.assets'] .kind")
        # after the kinds, newest first, each once
        assert [t.get_attribute("id") for t in tiles if "-upload-" in t.get_attribute("id")] == [
            tile(driver, a) for a in listed]
        assert not driver.find_elements("id", tile(driver, png))
        want = keyed.get(f"/assets/{mesh}/thumbnail.png").content
        assert wait(lambda: (p := picture(driver, mesh)) and p["state"] == "shown" and p["png"] and p, 60,
                    "the mesh's picture") == {"state": "shown", "w": 128, "h": 96, "png": want}
        assert wait(lambda: picture(driver, bare)["state"] == "none", 60, "the placeholder")
        assert driver.find_element("id", tile(driver, bare)).get_attribute("title") == "pipe.stl"
        # tick the mesh: the spec names it
        tick(driver, f"[id='{tile(driver, mesh)}'] input[type=checkbox]")
        (target,) = page_spec(driver)["targets"]
        assert target["assets"][-1] == {"asset_id": mesh}
        # the preview is the spec's with the mesh: a worker renders what the page sends
        expected = server_preview(url, page_spec(driver), 0, {"X-API-Key": KEY})
        wait(lambda: preview_src(driver) == expected["images"]["image"], 90, "the preview with the uploaded mesh")
        # a mesh uploaded from the page: a tile with its picture at once, and again after a reload
        driver.find_element("id", "upload-targets.0.assets").send_keys(str(upload))
        crate = wait(lambda: next((i["asset_id"] for i in every_asset(keyed) if i["filename"] == "crate.obj"), None),
                     90, "the page's upload")
        assert wait(lambda: (p := picture(driver, crate)) and p["png"], 60, "its picture") == keyed.get(
            f"/assets/{crate}/thumbnail.png").content
        open_page(driver, url)  # a reload: the page lists them from GET /assets
        for asset_id in (mesh, crate):
            assert wait(lambda a=asset_id: (p := picture(driver, a)) and p["png"], 60, "a picture after the reload") \
                == keyed.get(f"/assets/{asset_id}/thumbnail.png").content
        # read in one script: the picker may redraw between a find and a read of its tiles
        ids = driver.execute_script(
            "return [...document.querySelectorAll(\"[id='f-targets.0.assets'] .kind\")].map((e) => e.id)")
        assert len(ids) == len(set(ids)) and tile(driver, crate) in ids  # the key given twice: listed once
        # the distractors' picker lists them too
        assert driver.find_elements("id", f"pick-distractors.assets-upload-{crate[:12]}")
        # the crates alone in the class: the preview shows them (a worker renders it)
        for asset in ("urchin", f"upload-{crate[:12]}"):
            tick(driver, f"[id='pick-targets.0.assets-{asset}'] input[type=checkbox]")
        expected = server_preview(url, page_spec(driver), 0, {"X-API-Key": KEY})
        wait(lambda: preview_src(driver) == expected["images"]["image"], 90, "the preview of the crates")
        driver.execute_script("window.scrollTo(0, 0); const c = document.getElementById('controls');"
                              "c.scrollTop = document.getElementById('f-targets.0.assets').offsetTop - c.offsetTop;")
        shot(driver, "playground-uploads")



def tick(driver, selector: str) -> None:
    """Click the checkbox at `selector` in one script: the picker redraws its tiles as pictures and previews arrive,
    so an element found in one call may be stale by the next."""
    assert driver.execute_script("const e = document.querySelector(arguments[0]); if (!e) return false; e.click(); "
                                 "return true;", selector), f"no {selector} on the page"


def _png() -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (6, 4), (20, 90, 30)).save(buf, format="PNG")
    return buf.getvalue()
