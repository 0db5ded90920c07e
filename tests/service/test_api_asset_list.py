"""The uploaded assets' list (GET /assets) and each mesh's picture (GET /assets/{id}/thumbnail.png), over real HTTP
with real Redis and moto's S3: every sidecar listed once, newest first, with what its upload answered; the picture
is the one seasynth.api.mesh_thumbnail draws of the mesh as workers load it, kept, cacheable, and drawn for a mesh
stored without one; bad parameters are 4xx, never 5xx, and a mesh without a picture still lists."""

from __future__ import annotations

import io
import json
from datetime import UTC, datetime

import httpx
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from service_stack import Stack

from seasynth.api import mesh_thumbnail
from seasynth.service.shards import asset_info_key, asset_thumbnail_key


@pytest.fixture(scope="module")
def api(infra: Stack):
    proc, url = infra.start_api({"SEASYNTH_FRAME_TIMEOUT_S": "2"})
    with httpx.Client(base_url=url, timeout=60) as c:
        yield c
    proc.stop()


def box_ply(extents) -> bytes:
    return trimesh.creation.box(extents=extents).export(file_type="ply")


def expected_picture(data: bytes, file_type: str) -> bytes:
    mesh = trimesh.load(io.BytesIO(data), file_type=file_type, force="mesh")
    return mesh_thumbnail.png(mesh.vertices, mesh.faces)


def listed(api) -> list[dict]:
    """Every item, following `next` from the first page of 7."""
    items, url = [], "/assets?limit=7"
    while url:
        page = api.get(url)
        assert page.status_code == 200, page.text
        body = page.json()
        assert len(body["items"]) <= body["limit"] == 7
        items += body["items"]
        url = body["next"]
    return items


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(extents=st.lists(st.tuples(*[st.floats(0.05, 3.0)] * 3), min_size=1, max_size=3))
def test_every_upload_lists_once_newest_first_as_its_upload_answered(api, services, extents):
    before = datetime.now(UTC).replace(microsecond=0)
    answers, statuses = [], []
    for k, e in enumerate(extents):
        r = api.post("/assets", files={"file": (f"box{k}.ply", box_ply(e))})
        assert r.status_code in (200, 201), r.text
        answers.append(r.json())
        statuses.append(r.status_code)
    image = api.post("/assets", files={"file": ("sand.png", _png(len(extents)))})
    assert image.status_code in (200, 201), image.text
    items = listed(api)
    sidecars = {o.key for o in services.store.list("assets/") if o.key.count("/") == 1 and o.key.endswith(".json")}
    assert sorted(asset_info_key(i["asset_id"]) for i in items) == sorted(sidecars)  # each once, none else
    times = [datetime.fromisoformat(i["uploaded_at"]) for i in items]
    assert times == sorted(times, reverse=True)
    by_id = {i["asset_id"]: i for i in items}
    for a in answers:
        got = by_id[a["asset_id"]]
        assert {k: got[k] for k in a} == a
        assert got["thumbnail"] == f"/assets/{a['asset_id']}/thumbnail.png"
    for a, status in zip(answers, statuses):
        if status == 201:  # first uploaded now (the same extents may come again in a later example)
            assert datetime.fromisoformat(by_id[a["asset_id"]]["uploaded_at"]) >= before
    assert by_id[image.json()["asset_id"]]["thumbnail"] is None
    assert api.get("/assets").json()["total"] == len(sidecars)


def _png(seed: int) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (5, 4), (seed % 256, 90, 30)).save(buf, format="PNG")
    return buf.getvalue()


def test_a_meshs_picture_is_the_one_drawn_of_it_kept_and_cacheable(api, services):
    data = trimesh.creation.icosphere(2).export(file_type="stl")
    r = api.post("/assets", files={"file": ("ball.stl", data)})
    asset_id = r.json()["asset_id"]
    got = api.get(f"/assets/{asset_id}/thumbnail.png")
    assert got.status_code == 200 and got.headers["content-type"] == "image/png"
    assert got.content == expected_picture(data, "stl")
    assert Image.open(io.BytesIO(got.content)).size == (128, 96)
    assert services.store.get_bytes(asset_thumbnail_key(asset_id)) == got.content  # drawn at upload
    assert got.headers["cache-control"] == "private, max-age=86400"
    again = api.get(f"/assets/{asset_id}/thumbnail.png", headers={"If-None-Match": got.headers["etag"]})
    assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == got.headers["etag"]
    other = api.get(f"/assets/{asset_id}/thumbnail.png", headers={"If-None-Match": '"something-else"'})
    assert other.status_code == 200 and other.content == got.content


def test_a_mesh_stored_without_a_picture_gets_it_drawn_once_asked(api, services):
    """As a mesh uploaded before pictures were drawn: the first request draws and keeps it."""
    data = box_ply((0.4, 1.3, 0.2))
    asset_id = api.post("/assets", files={"file": ("plank.ply", data)}).json()["asset_id"]
    services.store.delete(asset_thumbnail_key(asset_id))
    got = api.get(f"/assets/{asset_id}/thumbnail.png")
    assert got.status_code == 200 and got.content == expected_picture(data, "ply")
    assert services.store.get_bytes(asset_thumbnail_key(asset_id)) == got.content


def test_a_mesh_without_a_picture_still_lists_and_its_picture_is_404_naming_why(api, services):
    data = box_ply((0.9, 0.2, 0.2))
    asset_id = api.post("/assets", files={"file": ("beam.ply", data)}).json()["asset_id"]
    services.store.delete(asset_thumbnail_key(asset_id))
    why = asset_thumbnail_key(asset_id).removesuffix(".png") + ".json"
    services.store.put_bytes(why, json.dumps({"error": "MemoryError: drawing it"}).encode())
    try:
        r = api.get(f"/assets/{asset_id}/thumbnail.png")
        assert r.status_code == 404
        assert r.json()["detail"] == f"asset {asset_id} (beam.ply): no picture could be drawn (MemoryError: drawing it)"
        assert [i["thumbnail"] for i in listed(api) if i["asset_id"] == asset_id] == [
            f"/assets/{asset_id}/thumbnail.png"]
    finally:
        services.store.delete(why)
    # A mesh whose stored file is gone (an upload that died between sidecar and object): 404, nothing kept.
    services.store.delete(asset_thumbnail_key(asset_id))
    services.store.delete(f"assets/{asset_id}")
    r = api.get(f"/assets/{asset_id}/thumbnail.png")
    assert r.status_code == 404 and f"assets/{asset_id}" in r.json()["detail"]
    assert api.post("/assets", files={"file": ("beam.ply", data)}).status_code == 200  # the object is back
    assert api.get(f"/assets/{asset_id}/thumbnail.png").content == expected_picture(data, "ply")


@pytest.mark.parametrize("query, where", [
    ("offset=-1", "offset"), ("limit=0", "limit"), ("limit=101", "limit"), ("limit=ten", "limit"),
    ("offset=1.5", "offset"), ("offset=10000000000", "offset"), ("limit=", "limit"),
])
def test_bad_list_parameters_are_422_naming_the_parameter(api, query, where):
    r = api.get(f"/assets?{query}")
    assert r.status_code == 422, r.text
    assert [line.split(":")[0] for line in r.json()["errors"]] == [f"query.{where}"]


def test_pictures_of_no_mesh_are_404(api):
    image = api.post("/assets", files={"file": ("flat.png", _png(7))}).json()["asset_id"]
    for asset_id, detail in [
        ("0" * 64, f"no asset '{'0' * 64}'"),
        ("not-an-id", "no asset 'not-an-id'"),
        ("A" * 64, f"no asset '{'A' * 64}'"),
        (image, f"asset {image} (flat.png) is an image (png): pictures are drawn for meshes"),
    ]:
        r = api.get(f"/assets/{asset_id}/thumbnail.png")
        assert (r.status_code, r.json()["detail"]) == (404, detail)
