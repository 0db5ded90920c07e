"""The API under abuse and outages, over real HTTP with real Redis and moto's S3: asset formats fixed by the first
upload, uploads that must load, body limits and the key checked before any body is read, a broker or a bucket
that is down, manifest pages, strict spec types, plain frame indices and the frame worker's failures."""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import io
import json
import socket
import struct
import tarfile
import threading
import time
import urllib.parse
import zlib
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import pytest

from service.errors import Unavailable
from service.record_types import ShardCommit
from service.records import Records, push_reply
from service.shards import asset_info_key, asset_key, shard_count
from service.storage import LocalStore, S3Store
from service_stack import Stack, free_port, tiny_spec, wait_for, wait_state

VERSION = "0.0.0-hardening"  # no worker consumes these queues: what the API publishes stays where it was put
KEY = "k-hardening"


@contextmanager
def serving(app) -> Iterator[str]:
    """uvicorn serving `app` on a free port in a thread of this process."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 15, "uvicorn")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)


@pytest.fixture(scope="module")
def settings(infra: Stack):
    return infra.settings(key_prefix="hardening", worker_version=VERSION, max_spec_bytes=4096,
                          max_asset_bytes=20_000, api_keys=KEY, frame_timeout_s=20, retry_after_s=9)


@pytest.fixture(scope="module")
def services(settings):
    from api.deps import open_services

    s = open_services(settings)
    yield s
    s.close()


@pytest.fixture
def serve(settings, services):
    """serve(**replaced services) -> base URL of an API on those services (real Redis and S3 unless replaced)."""
    from api.main import create_app

    stack = []

    def start(**replace) -> str:
        ctx = serving(create_app(settings, dataclasses.replace(services, **replace)))
        stack.append(ctx)
        return ctx.__enter__()

    yield start
    for ctx in reversed(stack):
        ctx.__exit__(None, None, None)


@pytest.fixture
def api(serve) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=serve(), headers={"X-API-Key": KEY}, timeout=60) as c:
        yield c


def dead_producer():
    """A Celery producer whose broker refuses connections."""
    from celery import Celery

    return Celery("dead", broker=f"redis://127.0.0.1:{free_port()}/0", set_as_current=False)


def dead_store(bucket: str) -> S3Store:
    """A bucket on an endpoint where nothing listens."""
    import boto3
    from botocore.config import Config

    cfg = Config(retries={"max_attempts": 1, "mode": "standard"}, connect_timeout=2, signature_version="s3v4")
    return S3Store(boto3.client("s3", endpoint_url=f"http://127.0.0.1:{free_port()}", config=cfg), bucket)


def raw_http(url: str, head: str, parts: list[bytes] = (), timeout: float = 5.0) -> tuple[int, dict, bytes]:
    """Send a request head and body parts by hand; the response (status, headers, body). A server that waits for
    more body than was sent runs into `timeout` (socket.timeout)."""
    u = urllib.parse.urlsplit(url)
    with socket.create_connection((u.hostname, u.port), timeout=timeout) as s:
        s.sendall(head.replace("\n", "\r\n").encode() + b"\r\n")
        for part in parts:
            try:
                s.sendall(part)
            except OSError:  # the server answered and closed: read the answer
                break
        data = b""
        while b"\r\n\r\n" not in data:
            got = s.recv(65536)
            if not got:
                break
            data += got
        top, _, body = data.partition(b"\r\n\r\n")
        lines = top.decode("latin-1").split("\r\n")
        headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
        while len(body) < int(headers.get("content-length", 0)):
            got = s.recv(65536)
            if not got:
                break
            body += got
    return int(lines[0].split()[1]), headers, body


def chunk(data: bytes) -> bytes:
    return f"{len(data):x}\r\n".encode() + data + b"\r\n"


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


# --- the gate: the key first, then the body's size, before any body is read


def test_an_unauthenticated_request_is_refused_before_its_body_is_read(serve):
    url = serve()
    for path in ("/assets", "/datasets"):
        # 100 MB announced and none sent: a server reading the body first would wait here until the timeout.
        status, headers, body = raw_http(url, f"POST {path} HTTP/1.1\nHost: x\nContent-Type: application/json\n"
                                              f"Content-Length: 100000000\n")
        assert status == 401 and headers["www-authenticate"] == 'Bearer realm="seasynth"', body
        assert json.loads(body)["errors"] == ["a valid API key is required (X-API-Key header or Authorization: Bearer)"]
        status, _, _ = raw_http(url, f"POST {path} HTTP/1.1\nHost: x\nTransfer-Encoding: chunked\nX-API-Key: nope\n"
                                     "Content-Type: multipart/form-data; boundary=b\n", [chunk(b"x" * 1000)])
        assert status == 401


def test_bodies_over_the_limit_are_refused_before_or_while_they_stream(serve, settings):
    url = serve()
    spec_limit, upload_limit = settings.max_spec_bytes, settings.max_asset_bytes + 64 * 1024
    part_head = b'--b\r\nContent-Disposition: form-data; name="file"; filename="x.obj"\r\n\r\n'
    cases = [("/datasets", "application/json", b"", spec_limit, f"{spec_limit} bytes (SEASYNTH_MAX_SPEC_BYTES)"),
             ("/assets", "multipart/form-data; boundary=b", part_head, upload_limit,
              f"{settings.max_asset_bytes} bytes of file (SEASYNTH_MAX_ASSET_BYTES) plus 65536 bytes of multipart "
              "framing")]
    for path, content_type, first, limit, named in cases:
        # By Content-Length, with no body sent at all.
        status, _, body = raw_http(url, f"POST {path} HTTP/1.1\nHost: x\nX-API-Key: {KEY}\n"
                                        f"Content-Length: {limit + 1}\n")
        assert status == 413 and json.loads(body)["errors"] == [
            f"request body of {limit + 1} bytes is over the limit of {named}"]
        # Chunked: refused once the limit is passed, although the body never ends.
        status, _, body = raw_http(url, f"POST {path} HTTP/1.1\nHost: x\nX-API-Key: {KEY}\n"
                                        f"Content-Type: {content_type}\nTransfer-Encoding: chunked\n",
                                   [chunk(first + b" " * 1000)] + [chunk(b" " * 1000)] * (limit // 1000))
        assert status == 413, body
        (line,) = json.loads(body)["errors"]
        assert line.startswith(f"request body is over the limit of {named} (stopped after ")


def test_a_spec_of_exactly_the_limit_is_read(api, settings):
    spec = json.dumps(tiny_spec()).encode()
    exact = spec + b" " * (settings.max_spec_bytes - len(spec))
    r = api.post("/datasets", content=exact, headers={"content-type": "application/json"})
    assert r.status_code == 202, r.text
    assert api.post(f"/datasets/{r.json()['id']}/cancel").json()["state"] == "cancelled"
    r = api.post("/datasets", content=exact + b" ", headers={"content-type": "application/json"})
    assert r.status_code == 413 and "SEASYNTH_MAX_SPEC_BYTES" in r.json()["detail"]


def test_a_file_over_the_asset_limit_within_the_framing_allowance_is_refused(api, settings):
    r = api.post("/assets", files={"file": ("big.obj", b"#" * (settings.max_asset_bytes + 1))})
    assert r.status_code == 413
    assert r.json()["errors"] == [f"big.obj: over the limit of {settings.max_asset_bytes} bytes "
                                  "(SEASYNTH_MAX_ASSET_BYTES)"]


def test_keys_headers_and_health(serve):
    url = serve()
    assert httpx.get(f"{url}/datasets", headers={"X-API-Key": "", "Authorization": f"Bearer {KEY}"}).status_code == 200
    assert httpx.get(f"{url}/datasets", headers={"Authorization": f"bearer {KEY}"}).status_code == 200
    assert httpx.get(f"{url}/datasets", headers={"X-API-Key": ""}).status_code == 401
    assert httpx.get(f"{url}/datasets", headers={"Authorization": "Bearer"}).status_code == 401
    assert httpx.get(f"{url}/datasets", headers={"X-API-Key": "nope", "Authorization": "Basic x"}).status_code == 401
    assert httpx.get(f"{url}/nowhere").status_code == 401  # nothing is probed without a key
    assert httpx.get(f"{url}/nowhere", headers={"X-API-Key": KEY}).json()["errors"] == ["Not Found"]
    for path in ("/healthz", "/readyz"):  # probes carry no key
        head = httpx.head(f"{url}{path}")
        assert head.status_code == 200 and head.content == b"", path
        assert httpx.get(f"{url}{path}").json()["status"] == "ok"


# --- the broker or the bucket down


def hardening_keys(services) -> set[str]:
    return set(services.records.r.scan_iter(match="hardening:ds:*"))


def test_a_dataset_the_broker_cannot_take_is_503_and_leaves_no_record(serve, services, settings):
    url = serve(producer=dead_producer())
    before_ids, before_keys = services.records.list_ids(0, 10**6), hardening_keys(services)
    bucket_records = {o.key for o in services.store.list("records/")}  # service.recovery's creation records
    r = httpx.post(f"{url}/datasets", json=tiny_spec(), headers={"X-API-Key": KEY}, timeout=60)
    assert r.status_code == 503 and r.headers["retry-after"] == str(settings.retry_after_s), r.text
    assert r.json()["detail"].startswith("task broker unavailable: could not publish seasynth.plan_dataset (")
    assert services.records.list_ids(0, 10**6) == before_ids
    assert hardening_keys(services) == before_keys
    assert {o.key for o in services.store.list("records/")} == bucket_records


def new_record(records: Records, *, frames: int, shard_size: int = 1, age_s: float = 0.0) -> str:
    import uuid

    dataset_id = uuid.uuid4().hex
    records.create(dataset_id, tiny_spec(frames=frames, shard_size=shard_size), seed=7, code_version=VERSION,
                   frames=frames, shard_size=shard_size, shards=shard_count(frames, shard_size),
                   now=time.time() - age_s)
    return dataset_id


def commit(records: Records, dataset_id: str, index: int, data: bytes, store=None) -> ShardCommit:
    key = f"datasets/{dataset_id}/shards/shard-{index:06d}.tar"
    if store is not None:
        store.put_bytes(key, data)
    c = ShardCommit(index=index, key=key, first_frame=index, frame_count=1, sha256=hashlib.sha256(data).hexdigest(),
                    bytes=len(data), code_version=VERSION, renderer="test")
    records.commit(dataset_id, c)
    return c


def test_status_reads_survive_a_broker_outage_and_retry_the_nudge(serve, services):
    url = serve(producer=dead_producer())
    headers = {"X-API-Key": KEY}
    records = services.records
    # Every shard in but not finalised: a status read publishes a reconcile, and cannot.
    done = new_record(records, frames=2)
    for i in range(2):
        records.start_attempt(done, i, 3, {"since": time.time()})
        commit(records, done, i, b"shard %d" % i)
        records.end_attempt(done, i)
    r = httpx.get(f"{url}/datasets/{done}", headers=headers)
    assert r.status_code == 200, r.text
    assert (r.json()["state"], r.json()["shards_done"], r.json()["frames_done"]) == ("running", 2, 2)
    # Stalled: the sweep claims its lock, cannot publish, and gives the lock back for the next read.
    stalled = new_record(records, frames=3, age_s=10_000)
    for path in (f"/datasets/{stalled}", "/datasets?limit=100"):
        r = httpx.get(f"{url}{path}", headers=headers)
        assert r.status_code == 200, r.text
    assert records.claim_sweep(stalled, 60)
    # Asked for explicitly, the reconcile is the answer: 503.
    r = httpx.post(f"{url}/datasets/{stalled}/reconcile", headers=headers)
    assert r.status_code == 503 and r.headers["retry-after"] == "9"
    assert "task broker unavailable" in r.json()["detail"]
    r = httpx.get(f"{url}/datasets/{done}/frames/0", headers=headers)
    assert r.status_code == 503 and "seasynth.render_frame" in r.json()["detail"]


def test_a_purge_the_bucket_fails_is_503_and_can_be_repeated(serve, services, settings):
    records = services.records
    dataset_id = new_record(records, frames=3)
    for i in range(3):
        commit(records, dataset_id, i, b"tar %d" % i, services.store)
    prefix = f"datasets/{dataset_id}/"
    keys = sorted(o.key for o in services.store.list(prefix))
    assert len(keys) == 3
    headers = {"X-API-Key": KEY}

    down = serve(store=dead_store(settings.s3_bucket))
    r = httpx.delete(f"{down}/datasets/{dataset_id}", headers=headers, timeout=60)
    assert r.status_code == 503 and r.headers["retry-after"] == "9", r.text
    assert f"s3://{settings.s3_bucket}/{prefix}" in r.json()["detail"]
    rec = records.get(dataset_id)
    assert (rec.state, rec.purged) == ("cancelled", False)  # cancelled at once; not purged: objects remain
    assert sorted(o.key for o in services.store.list(prefix)) == keys

    up = serve()
    assert httpx.get(f"{up}/datasets/{dataset_id}", headers=headers).json()["state"] == "cancelled"  # still there
    r = httpx.delete(f"{up}/datasets/{dataset_id}", headers=headers)
    assert r.status_code == 204 and r.content == b"", r.text
    assert list(services.store.list(prefix)) == []
    assert records.get(dataset_id).purged  # the tombstone workers read
    assert httpx.get(f"{up}/datasets/{dataset_id}", headers=headers).status_code == 404
    assert httpx.delete(f"{up}/datasets/{dataset_id}", headers=headers).status_code == 404


class PartialDeleteClient:
    """An S3 client whose bulk delete reports one key it could not delete (HTTP 200 with Errors)."""

    def __init__(self, keys: list[str]):
        self.keys = keys

    def get_paginator(self, name):
        keys = self.keys

        class Pages:
            def paginate(self, **kw):
                return [{"Contents": [{"Key": k, "Size": 1} for k in keys]}]

        return Pages()

    def delete_objects(self, Bucket, Delete):
        return {"Errors": [{"Key": self.keys[1], "Code": "AccessDenied", "Message": "Access Denied"}]}


def test_a_bulk_delete_that_leaves_objects_is_an_error():
    store = S3Store(PartialDeleteClient(["d/a", "d/b", "d/c"]), "bkt")
    with pytest.raises(Unavailable) as info:
        store.delete_prefix("d/")
    assert str(info.value) == "s3://bkt/d/: 1 objects not deleted, e.g. d/b (AccessDenied: Access Denied)"


# --- manifest pages


def test_manifest_pages_by_shard_index_with_totals_of_the_whole(api, services):
    records = services.records
    dataset_id = new_record(records, frames=7)
    commits = {i: commit(records, dataset_id, i, b"shard bytes %d" % i, services.store) for i in (0, 1, 2, 4, 6)}
    pages, link = [], f"/datasets/{dataset_id}/manifest?limit=3"
    while link:
        r = api.get(link)
        assert r.status_code == 200, r.text
        pages.append(r.json())
        link = r.json()["next"]
    assert [(p["start"], p["limit"], [s["index"] for s in p["shards"]]) for p in pages] == [
        (0, 3, [0, 1, 2]), (3, 3, [4]), (6, 3, [6])]
    assert [p["next"] for p in pages] == [f"/datasets/{dataset_id}/manifest?start=3&limit=3",
                                         f"/datasets/{dataset_id}/manifest?start=6&limit=3", None]
    for p in pages:
        assert (p["complete"], p["shards_done"], p["frames_done"], p["shards_total"]) == (False, 5, 5, 7)
        assert (p["seed"], p["code_version"], p["spec"]) == (7, VERSION, tiny_spec(frames=7, shard_size=1))
    for s in (s for p in pages for s in p["shards"]):
        c = commits[s["index"]]
        assert (s["key"], s["first_frame"], s["frame_count"], s["sha256"], s["bytes"]) == (
            c.key, c.first_frame, c.frame_count, c.sha256, c.bytes)
        assert hashlib.sha256(httpx.get(s["url"]).content).hexdigest() == c.sha256
    whole = api.get(f"/datasets/{dataset_id}/manifest").json()  # the default page covers 1000 shard indices
    assert (whole["start"], whole["limit"], whole["next"]) == (0, 1000, None)
    assert [s["index"] for s in whole["shards"]] == [0, 1, 2, 4, 6]
    for bad in ({"limit": 0}, {"limit": 10_001}, {"start": -1}, {"limit": "many"}):
        assert api.get(f"/datasets/{dataset_id}/manifest", params=bad).status_code == 422, bad


def shard_tar(index: int) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        data = f"label of frame {index}\n".encode()
        info = tarfile.TarInfo(f"label_2/{index:06d}.txt")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def test_fetch_follows_the_manifest_pages(serve, services, tmp_path):
    from service.fetch import fetch_dataset

    url = serve()
    records = services.records
    dataset_id = new_record(records, frames=2001)  # three default pages, one committed shard on each
    for i in (0, 1000, 2000):
        commit(records, dataset_id, i, shard_tar(i), services.store)
    out = tmp_path / "out"
    report = fetch_dataset(url, dataset_id, out, api_key=KEY, partial=True, progress=False)
    assert (report.shards_total, report.shards_fetched, report.files) == (3, 3, 3)
    assert sorted(p.name for p in (out / "label_2").iterdir()) == ["000000.txt", "001000.txt", "002000.txt"]
    man = json.loads((out / "manifest.json").read_text())
    assert [s["index"] for s in man["shards"]] == [0, 1000, 2000]
    assert not {"start", "limit", "next"} & set(man) and man["shards_done"] == 3 and not man["complete"]


class ExpiringURLs:
    """A store whose URLs point at a local HTTP server that refuses the first URL handed out for each key with 403,
    as S3 refuses an expired presigned URL, and serves the object at any later one."""

    def __init__(self, inner):
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        self.inner, self.issued, self._lock = inner, {}, threading.Lock()
        store = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                generation, key = self.path.lstrip("/").split("/", 1)
                if generation == "1":
                    status = 403
                    body = b"<Error><Code>AccessDenied</Code><Message>Request has expired</Message></Error>"
                else:
                    body, status = store.inner.get_bytes(key), 200
                self.send_response(status)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def url(self, key: str) -> str:
        with self._lock:
            self.issued[key] = n = self.issued.get(key, 0) + 1
        return f"http://127.0.0.1:{self.server.server_port}/{n}/{key}"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def test_fetch_asks_the_api_again_for_urls_the_store_refuses(serve, services, tmp_path):
    """A download that outlasts its presigned URLs: each refused URL is replaced by a fresh one from the manifest."""
    from service.fetch import fetch_dataset

    store = ExpiringURLs(services.store)
    try:
        url = serve(store=store)
        dataset_id = new_record(services.records, frames=3)
        for i in range(3):
            commit(services.records, dataset_id, i, shard_tar(i), services.store)
        out = tmp_path / "out"
        report = fetch_dataset(url, dataset_id, out, api_key=KEY, progress=False)
        assert (report.shards_total, report.shards_fetched, report.files) == (3, 3, 3)
        # Each shard's URL: once in the manifest (refused), once asked for again (served).
        assert sorted(store.issued.values()) == [2, 2, 2]
        for i in range(3):
            assert (out / f"label_2/{i:06d}.txt").read_text() == f"label of frame {i}\n"
    finally:
        store.close()


# --- strict types, frame indices, malformed JSON


@pytest.mark.parametrize(
    ("change", "field"),
    [({"seed": True}, "seed"), ({"seed": "7"}, "seed"), ({"frames": 2.0}, "frames"),
     ({"shard_size": "2"}, "shard_size"), ({"camera": {"width": 32.0, "height": 24}}, "camera.width"), ({"outputs": {"depth": 1}}, "outputs.depth"),
     ({"outputs": {"meta": "false"}}, "outputs.meta")],
)
def test_the_api_takes_ints_and_bools_strictly(api, change, field):
    r = api.post("/datasets", json=tiny_spec(**change))
    assert r.status_code == 422, r.text
    (line,) = r.json()["errors"]
    assert line.startswith(f"{field}: Input should be a valid "), line


def test_lists_over_their_limit_are_refused_naming_field_and_limit(client):
    spec = tiny_spec(targets={"assets": [{"procedural": "urchin"}] * 257})  # 8 KiB: within the default 1 MiB
    r = client.post("/datasets", json=spec)
    assert r.status_code == 422
    assert r.json()["errors"] == ["targets.assets: List should have at most 256 items after validation, not 257"]


@pytest.mark.parametrize("body", [b"{", b'{"seed": 1,}', b"\xff\xfe", b"{'seed': 1}", b"<xml/>"])
def test_malformed_json_is_400_saying_so(api, body):
    r = api.post("/datasets", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400, r.text
    (line,) = r.json()["errors"]
    assert line.startswith("malformed JSON in the request body at character "), line


def test_frame_indices_are_plain_digits(api, services):
    dataset_id = new_record(services.records, frames=20)
    queue = services.raw_redis
    from service.queues import frame_queue

    before = queue.llen(frame_queue(VERSION))
    for index in ("%201", "+1", "1.0", "1_0", "-0", "1e1", "%EF%BC%91", "1%0A"):
        r = api.get(f"/datasets/{dataset_id}/frames/{index}")
        assert r.status_code == 404, (index, r.status_code, r.text)
        assert "a frame index is written in decimal digits" in r.json()["detail"], r.text
    assert api.get(f"/datasets/{dataset_id}/frames/20").status_code == 404  # digits, but past the last frame
    assert queue.llen(frame_queue(VERSION)) == before  # nothing was sent to a frame worker


def answer_frame(raw, header: dict, body: bytes = b"") -> tuple[str, int, str]:
    """Play a frame worker: take one frame task of VERSION's queue and answer it with `header`."""
    from service.queues import frame_queue

    _, message = raw.blpop([frame_queue(VERSION)], timeout=15)
    dataset_id, index, part, reply_key = json.loads(base64.b64decode(json.loads(message)["body"]))[0]
    push_reply(raw, reply_key, header, body, ttl_s=60)
    return dataset_id, index, part


@pytest.mark.parametrize(
    ("header", "status", "detail"),
    [
        ({"ok": False, "status": 500, "error": "ValueError: boom"}, 502,
         "frame 3 of dataset {id} failed on the frame worker: ValueError: boom"),
        ({"ok": False, "status": 503, "error": "renderer X started it"}, 503,
         "frame 3 of dataset {id}: renderer X started it"),
        ({"ok": False, "status": 422, "error": "asset a.obj: no triangles"}, 422,
         "frame 3 of dataset {id}: asset a.obj: no triangles"),
        ({"ok": False, "status": 404, "error": "frame 3 has no depth"}, 404, "frame 3 has no depth"),
        ({"ok": True, "name": "image_2/000003.png"}, 200, None),
    ],
)
def test_frame_worker_failures_map_to_honest_statuses(api, services, header, status, detail):
    dataset_id = new_record(services.records, frames=5)
    got: dict = {}
    getter = threading.Thread(target=lambda: got.update(r=api.get(f"/datasets/{dataset_id}/frames/3")))
    getter.start()
    assert answer_frame(services.raw_redis, header, b"\x89PNG" if header["ok"] else b"") == (dataset_id, 3, "image")
    getter.join(30)
    r = got["r"]
    assert r.status_code == status, r.text
    if detail is None:
        assert r.content == b"\x89PNG"
    else:
        assert r.json()["detail"] == detail.format(id=dataset_id)
        assert ("retry-after" in r.headers) == (status == 503)


@pytest.mark.parametrize("body", [
    b"[" * 2000 + b"]" * 2000,  # deeper than the JSON decoder's recursion limit
    b'{"a":' * 500 + b"1" + b"}" * 500,
    b'{"camera": ' + b"[" * 900 + b"]" * 900 + b"}",  # parses, then fails validation deep inside
], ids=["arrays-2000", "objects-500", "nested-in-a-field"])
def test_deeply_nested_json_within_the_size_limit_is_a_4xx_with_a_body(api, settings, body):
    assert len(body) <= settings.max_spec_bytes
    r = api.post("/datasets", content=body, headers={"content-type": "application/json"})
    assert r.status_code in (400, 422), (r.status_code, r.text[:300])
    assert isinstance(r.json()["detail"], str) and r.json()["detail"]


@pytest.mark.parametrize("freeze", [True, False])
def test_a_server_app_freezes_what_exists_once_started_and_an_embedded_one_does_not(settings, services, freeze):
    """`seasynth serve` builds its app with freeze_gc: the collector's full passes then skip every object alive
    after startup (bench/load.py measured a 130 ms pause per pass without); an app embedded in another process
    (tests, bench/enqueue.py) leaves that process's collector as it was."""
    import gc

    from api.main import create_app

    before = [[]]  # a container, so the collector tracks it
    assert any(o is before for o in gc.get_objects())
    try:
        with serving(create_app(settings, services, freeze_gc=freeze)) as url:
            assert httpx.get(f"{url}/healthz").status_code == 200
            tracked = any(o is before for o in gc.get_objects())  # frozen objects are in no generation
            frozen = gc.get_freeze_count()
    finally:
        gc.unfreeze()  # this test process's collector sees everything again
    assert tracked is not freeze and (frozen > 0) is freeze
