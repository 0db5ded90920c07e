"""The API's requests under abuse, over real HTTP with real Redis and moto's S3: the key and the body's size
checked before any body is read, strict spec types, malformed JSON, plain frame indices and the frame worker's
failures."""

from __future__ import annotations

import base64
import json
import socket
import threading
import urllib.parse

import httpx
import pytest
from hardening import KEY, VERSION, api, new_record, serve, services, serving, settings  # noqa: F401 (fixtures)
from service_stack import tiny_spec

from seasynth.service.records.store import push_reply


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
    from seasynth.service.queues import frame_queue

    before = queue.llen(frame_queue(VERSION))
    for index in ("%201", "+1", "1.0", "1_0", "-0", "1e1", "%EF%BC%91", "1%0A"):
        r = api.get(f"/datasets/{dataset_id}/frames/{index}")
        assert r.status_code == 404, (index, r.status_code, r.text)
        assert "a frame index is written in decimal digits" in r.json()["detail"], r.text
    assert api.get(f"/datasets/{dataset_id}/frames/20").status_code == 404  # digits, but past the last frame
    assert queue.llen(frame_queue(VERSION)) == before  # nothing was sent to a frame worker


def answer_frame(raw, header: dict, body: bytes = b"") -> tuple[str, int, str]:
    """Play a frame worker: take one frame task of VERSION's queue and answer it with `header`."""
    from seasynth.service.queues import frame_queue

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

    from seasynth.api.main import create_app

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
