"""The API's asset uploads, over real HTTP with real Redis and moto's S3: formats fixed by the first upload, uploads
that must load, and datasets that need meshes and images."""

from __future__ import annotations

import hashlib
import io
import struct
import tarfile
import threading
import time
import zlib

import httpx
import pytest
from hardening import KEY, api, serve, services, settings  # noqa: F401 (fixtures)
from service_stack import Stack, tiny_spec, wait_state

from seasynth.service.shards import asset_info_key, asset_key
from seasynth.service.storage import LocalStore

# --- assets: formats fixed by the first upload, and checked


def triangle_obj(tag: str) -> bytes:
    return f"# {tag}\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode()


def ply_box(extent: float) -> bytes:
    import trimesh

    return trimesh.creation.box(extents=(extent, extent, extent)).export(file_type="ply")


def png(width: int = 4, height: int = 3, fmt: str = "PNG") -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (width, height), (10, 200, 30)).save(buf, format=fmt)
    return buf.getvalue()


def png_header_only(width: int, height: int) -> bytes:
    """A PNG that declares width x height pixels in a few dozen bytes."""
    def chunk_(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk_(b"IHDR", ihdr) + chunk_(b"IDAT", zlib.compress(b"\0")) + chunk_(b"IEND", b"")


def test_the_first_upload_fixes_an_assets_format_and_a_rendered_dataset_keeps_it(stack: Stack, client, services):
    data = ply_box(0.31)
    asset_id = hashlib.sha256(data).hexdigest()
    first = client.post("/assets", files={"file": ("box.ply", data)})
    assert first.status_code == 201, first.text
    assert first.json() == {"asset_id": asset_id, "filename": "box.ply", "bytes": len(data), "format": "ply",
                            "kind": "mesh"}
    sidecar = services.store.get_bytes(asset_info_key(asset_id))

    # The same bytes in the same format again: nothing changes, and the answer says so (200, the stored name).
    again = client.post("/assets", files={"file": ("other-name.PLY", data)})
    assert again.status_code == 200 and again.json() == first.json(), again.text
    # In another format: refused, naming the stored one; the sidecar workers read is untouched.
    for name, claimed in (("box.png", "an image (png)"), ("box.obj", "a mesh (obj)"), ("box.jpeg", "an image (jpeg)")):
        r = client.post("/assets", files={"file": (name, data)})
        assert r.status_code == 409, r.text
        assert r.json()["errors"] == [f"{name}: these bytes are already uploaded as asset {asset_id}, a mesh (ply), "
                                      f"first as 'box.ply'; they cannot also be {claimed}"]
    assert services.store.get_bytes(asset_info_key(asset_id)) == sidecar
    assert services.store.get_bytes(asset_key(asset_id)) == data

    spec = tiny_spec(frames=2, shard_size=1, targets={"count": [1, 1], "assets": [{"asset_id": asset_id}]})
    r = client.post("/datasets", json=spec)
    assert r.status_code == 202, r.text
    dataset_id = r.json()["id"]
    assert wait_state(client, dataset_id, {"succeeded", "failed"})["state"] == "succeeded"
    # A late hijack attempt changes nothing either: a frame re-rendered now (from the ply) is the one in its shard.
    assert client.post("/assets", files={"file": ("late.png", data)}).status_code == 409
    frame = client.get(f"/datasets/{dataset_id}/frames/1")
    assert frame.status_code == 200, frame.text
    (shard,) = [s for s in client.get(f"/datasets/{dataset_id}/manifest").json()["shards"] if s["first_frame"] == 1]
    with tarfile.open(fileobj=io.BytesIO(httpx.get(shard["url"]).content)) as tar:
        assert frame.content == tar.extractfile("image_2/000001.png").read()


@pytest.mark.parametrize("kind", ["local", "s3"])
def test_put_if_absent_lets_exactly_one_of_racing_writers_win(services, tmp_path, kind):
    store = LocalStore(tmp_path) if kind == "local" else services.store
    key = f"race/{time.monotonic_ns()}.json"
    go = threading.Barrier(8)
    won: list[bytes] = []

    def write(i: int) -> None:
        data = f"writer {i}".encode()
        go.wait()
        if store.put_bytes_if_absent(key, data):
            won.append(data)

    threads = [threading.Thread(target=write, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(won) == 1 and store.get_bytes(key) == won[0]
    assert store.put_bytes_if_absent(key, b"late") is False and store.get_bytes(key) == won[0]


BAD_UPLOADS = [
    ("words.obj", b"this is not a mesh\n", "words.obj: the obj mesh has no triangles"),
    ("point.obj", b"v 0 0 0\n", "point.obj: the obj mesh has no triangles"),
    ("header.ply", b"ply\nformat ascii 1.0\nend_header\n", "header.ply: the ply mesh has no triangles"),
    ("nothing.stl", b"solid x\nendsolid x\n", "nothing.stl: the stl mesh has no triangles"),
    ("junk.glb", b"glTF junk", "junk.glb: not a valid glb mesh ("),
    ("junk.png", b"\x89PNG junk", "junk.png: not an image Pillow can read (PNG or JPEG)"),
    ("text.jpg", b"just text", "text.jpg: not an image Pillow can read (PNG or JPEG)"),
    ("cut.png", png(64, 64)[:-40], "cut.png: cannot decode as an image ("),
    ("bomb.png", png_header_only(9000, 8000), "bomb.png: 9000x8000 pixels is over the limit of 67108864 pixels"),
]


@pytest.mark.parametrize(("name", "data", "error"), BAD_UPLOADS, ids=[b[0] for b in BAD_UPLOADS])
def test_uploads_that_do_not_load_are_refused_naming_the_upload(api, services, name, data, error):
    r = api.post("/assets", files={"file": (name, data)})
    assert r.status_code == 422, r.text
    (line,) = r.json()["errors"]
    assert line.startswith(error), line
    asset_id = hashlib.sha256(data).hexdigest()
    assert services.store.head(asset_key(asset_id)) is None
    assert services.store.head(asset_info_key(asset_id)) is None  # no sidecar to pin a format either


def test_meshes_and_images_that_load_are_stored(api, services):
    uploads = [("t.obj", triangle_obj("stored"), "obj", "mesh"), ("b.ply", ply_box(0.5), "ply", "mesh"),
               ("t.png", png(5, 4), "png", "image"), ("t.jpg", png(6, 4, "JPEG"), "jpeg", "image")]
    for name, data, fmt, kind in uploads:
        r = api.post("/assets", files={"file": (name, data)})
        assert r.status_code == 201, r.text
        assert (r.json()["format"], r.json()["kind"]) == (fmt, kind)
        assert services.store.get_bytes(asset_key(r.json()["asset_id"])) == data


def test_datasets_need_meshes_for_objects_and_an_image_for_the_texture(api):
    mesh = api.post("/assets", files={"file": ("k.obj", triangle_obj("kinds"))}).json()["asset_id"]
    image = api.post("/assets", files={"file": ("k.png", png(7, 7))}).json()["asset_id"]
    wrong = tiny_spec(targets={"assets": [{"asset_id": mesh}, {"asset_id": image}]},
                      terrain={"cells": 16, "variants": 1, "mesh": {"asset_id": image}, "texture": {"asset_id": mesh}})
    r = api.post("/datasets", json=wrong)
    assert r.status_code == 422, r.text
    assert r.json()["errors"] == [
        f"targets.assets.1.asset_id: asset {image} is an image (png); this field needs a mesh",
        f"terrain.mesh.asset_id: asset {image} is an image (png); this field needs a mesh",
        f"terrain.texture.asset_id: asset {mesh} is a mesh (obj); this field needs an image",
    ]
    right = tiny_spec(targets={"assets": [{"asset_id": mesh}]}, distractors={"assets": [{"asset_id": mesh}]},
                      terrain={"cells": 16, "variants": 1, "mesh": {"asset_id": mesh}, "texture": {"asset_id": image}})
    r = api.post("/datasets", json=right)
    assert r.status_code == 202, r.text
    assert api.post(f"/datasets/{r.json()['id']}/cancel").json()["state"] == "cancelled"


def binary_stl(triangles: int) -> bytes:
    """A binary STL of seeded random triangles (no two share a vertex: loading it holds every one)."""
    import numpy as np

    record = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rows = np.zeros(triangles, record)
    rows["v"] = np.random.default_rng(7).random((triangles, 3, 3), dtype=np.float32)
    return b"\0" * 80 + np.uint32(triangles).tobytes() + rows.tobytes()


def test_a_mesh_too_large_to_load_within_the_check_budget_is_413_and_the_api_stays_up(services, settings):
    """The check loads the mesh in a child process within SEASYNTH_UPLOAD_CHECK_MEMORY_MIB: a 5.4 M-triangle STL
    took 3.5 GB in the API process before. A small one passes under the same budget."""
    import dataclasses

    from hardening import serving

    from seasynth.api.main import create_app

    roomy = settings.model_copy(update={"max_asset_bytes": 64 * 2**20, "upload_check_memory_mib": 256})
    with serving(create_app(roomy, dataclasses.replace(services, settings=roomy))) as url:
        check_budget(url, services)


def check_budget(url: str, services) -> None:
    headers = {"X-API-Key": KEY}
    big = binary_stl(1_000_000)  # 50 MB
    r = httpx.post(f"{url}/assets", files={"file": ("scan.stl", big)}, headers=headers, timeout=120)
    assert r.status_code == 413, r.text
    assert r.json()["detail"] == ("scan.stl: loading the stl mesh needs more than 256 MiB "
                                  "(SEASYNTH_UPLOAD_CHECK_MEMORY_MIB); upload a smaller one (decimate it, or split "
                                  "it into assets)")
    assert services.store.head(asset_key(hashlib.sha256(big).hexdigest())) is None
    small = binary_stl(2000)
    r = httpx.post(f"{url}/assets", files={"file": ("rock.stl", small)}, headers=headers, timeout=120)
    assert r.status_code == 201, r.text
    assert httpx.get(f"{url}/healthz").status_code == 200
