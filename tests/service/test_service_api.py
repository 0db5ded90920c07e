"""The HTTP edge: client mistakes get 4xx naming the field or limit, never a 500; unknown ids are 404; API keys."""

from __future__ import annotations

import httpx
import pytest
from service_stack import Stack, tiny_spec

GARBAGE_IDS = ["0" * 32, "nope", "../../etc/passwd", "%00", "A" * 32, "0" * 33, "x" * 5000, "😀", "1;DROP"]


def test_health_and_docs(client):
    assert client.get("/healthz").json()["status"] == "ok"
    ready = client.get("/readyz").json()
    assert ready["checks"] == {"redis": "ok", "storage": "ok"}
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/datasets", "/datasets/{id}", "/datasets/{id}/manifest", "/datasets/{id}/frames/{index}",
            "/assets", "/healthz", "/readyz"} <= set(paths)


@pytest.mark.parametrize("bad_id", GARBAGE_IDS)
def test_unknown_or_malformed_ids_are_404_on_every_route(client, bad_id):
    for method, path in [("GET", "/datasets/{}"), ("GET", "/datasets/{}/manifest"),
                         ("GET", "/datasets/{}/frames/0"), ("DELETE", "/datasets/{}"),
                         ("POST", "/datasets/{}/cancel"), ("POST", "/datasets/{}/reconcile")]:
        r = client.request(method, path.format(bad_id))
        assert r.status_code == 404, (method, path, bad_id, r.status_code, r.text)


GARBAGE_BODIES = [
    b"", b"{", b"null", b"[]", b"42", b'"spec"', b"\xff\xfe", b'{"frames": "many"}', b'{"frames": -1}',
    b'{"frames": 1e400}', b'{"camera": []}', b'{"seed": 1.5}', b'{"targets": {"count": [3, 1]}}',
    b'{"outputs": {"depth": "perhaps"}}', b'{"unknown": 1}', b'{"frames": 99999999999999999999999}',
    b'{"camera": {"width": 100000}}', b'{"water": {"jerlov": ["XX"]}}',
]


@pytest.mark.parametrize("body", GARBAGE_BODIES)
def test_garbage_specs_get_4xx(client, body):
    r = client.post("/datasets", content=body, headers={"content-type": "application/json"})
    assert 400 <= r.status_code < 500, (body, r.status_code, r.text)
    assert r.json()["errors"]


def test_every_route_with_garbage_never_500(client):
    calls = [
        ("POST", "/datasets", {"content": b"<xml/>", "headers": {"content-type": "application/xml"}}),
        ("POST", "/datasets", {"data": {"a": "b"}}),
        ("GET", "/datasets", {"params": {"limit": "lots"}}),
        ("GET", "/datasets", {"params": {"limit": 0}}),
        ("GET", "/datasets", {"params": {"offset": -4}}),
        ("GET", "/datasets", {"params": {"offset": 10**30}}),
        ("GET", "/datasets/" + "0" * 32 + "/frames/-1", {}),
        ("GET", "/datasets/" + "0" * 32 + "/frames/zz", {}),
        ("GET", "/datasets/" + "0" * 32 + "/frames/" + "9" * 40, {}),
        ("GET", "/datasets/" + "0" * 32 + "/frames/0", {"params": {"part": "secrets"}}),
        ("POST", "/assets", {}),
        ("POST", "/assets", {"content": b"junk", "headers": {"content-type": "multipart/form-data; boundary=x"}}),
        ("POST", "/assets", {"files": {"file": ("evil.exe", b"MZ")}}),
        ("POST", "/assets", {"files": {"file": ("empty.obj", b"")}}),
        ("PUT", "/datasets", {}),
        ("GET", "/nowhere", {}),
    ]
    for method, path, kw in calls:
        r = client.request(method, path, **kw)
        assert 400 <= r.status_code < 500, (method, path, kw, r.status_code, r.text)
    # A path in an upload's name is reduced to its last component.
    mesh = b"# test_every_route_with_garbage_never_500\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"  # a new asset: 201
    r = client.post("/assets", files={"file": ("../../x.obj", mesh)})
    assert r.status_code == 201 and r.json()["filename"] == "x.obj"


def test_invalid_spec_names_the_field(client):
    r = client.post("/datasets", json=tiny_spec(camera={"width": 3, "height": 24}))
    assert r.status_code == 422
    assert any(e.startswith("camera.width:") for e in r.json()["errors"]), r.json()
    r = client.post("/datasets", json=tiny_spec(targets={"count": [5, 2]}))
    assert r.status_code == 422 and any(e.startswith("targets.count:") for e in r.json()["errors"])


def test_limits_are_named(client):
    # The spec's own cap (KITTI's six-digit names) is a spec error; the service's configured limit is 413.
    r = client.post("/datasets", json=tiny_spec(frames=1_000_001, shard_size=1000))
    assert r.status_code == 422 and r.json()["errors"] == ["frames: Input should be less than or equal to 1000000"]
    r = client.post("/datasets", json=tiny_spec(frames=500_001, shard_size=1000))
    assert r.status_code == 413 and "frames: 500001 is over the limit of 500000 (SEASYNTH_MAX_FRAMES)" in r.text
    ok = client.post("/datasets", json=tiny_spec(frames=500_000, shard_size=1000))
    assert ok.status_code == 202
    assert client.post(f"/datasets/{ok.json()['id']}/cancel").json()["state"] == "cancelled"


def test_shard_work_is_limited_by_the_task_time_limit(client, stack: Stack):
    """Within the static cap (600 megapixels per shard) but over what the configured time limit allows."""
    soft = stack.settings().task_soft_time_limit_s
    big = {"width": 1024, "height": 768}
    r = client.post("/datasets", json=tiny_spec(frames=100, shard_size=50, quality="high", camera=big))
    assert r.status_code == 413, r.text
    (line,) = r.json()["errors"]
    assert line.startswith("shard_size: 50 frames of 1024x768 at quality 'high'") and f"limit of {soft} s" in line
    assert "use shard_size <= 41" in line
    ok = client.post("/datasets", json=tiny_spec(frames=100, shard_size=41, quality="high", camera=big))
    assert ok.status_code == 202, ok.text
    assert client.post(f"/datasets/{ok.json()['id']}/cancel").json()["state"] == "cancelled"
    # A cheaper preset fits more frames per shard.
    fast = client.post("/datasets", json=tiny_spec(frames=100, shard_size=50, quality="draft", camera=big))
    assert fast.status_code == 202, fast.text
    assert client.post(f"/datasets/{fast.json()['id']}/cancel").json()["state"] == "cancelled"


def test_local_paths_and_unknown_assets_are_refused(client):
    r = client.post("/datasets", json=tiny_spec(targets={"assets": [{"path": "/etc/passwd"}]}))
    assert r.status_code == 422 and r.json()["errors"][0].startswith("targets.assets.0.path:")
    r = client.post("/datasets", json=tiny_spec(terrain={"texture": {"path": "https://example.com/t.png"}}))
    assert r.status_code == 422 and r.json()["errors"][0].startswith("terrain.texture.path:")
    r = client.post("/datasets", json=tiny_spec(distractors={"assets": [{"asset_id": "a" * 64}]}))
    assert r.status_code == 422 and r.json()["errors"][0].startswith("distractors.assets.0.asset_id: no uploaded")


def test_accepted_dataset_answers_with_links(client):
    r = client.post("/datasets", json=tiny_spec(frames=3, shard_size=2))
    assert r.status_code == 202
    body = r.json()
    assert body["shards_total"] == 2 and body["links"]["self"] == f"/datasets/{body['id']}"
    assert r.headers["location"] == body["links"]["self"]
    listed = client.get("/datasets", params={"limit": 1}).json()
    assert listed["items"][0]["id"] == body["id"] and listed["limit"] == 1


@pytest.fixture(scope="module")
def keyed_api(stack: Stack):
    proc, url = stack.start_api({"SEASYNTH_API_KEYS": "alpha, beta"})
    yield url
    proc.stop()


def test_api_keys(keyed_api):
    url = keyed_api
    assert httpx.get(f"{url}/healthz").status_code == 200
    assert httpx.get(f"{url}/readyz").status_code == 200
    for path in ("/datasets", "/datasets/" + "0" * 32):
        r = httpx.get(f"{url}{path}")
        assert r.status_code == 401 and "www-authenticate" in r.headers
        assert httpx.get(f"{url}{path}", headers={"X-API-Key": "gamma"}).status_code == 401
    assert httpx.post(f"{url}/datasets", json=tiny_spec()).status_code == 401
    assert httpx.get(f"{url}/datasets", headers={"X-API-Key": "beta"}).status_code == 200
    assert httpx.get(f"{url}/datasets", headers={"Authorization": "Bearer alpha"}).status_code == 200
    assert httpx.get(f"{url}/datasets/" + "0" * 32, headers={"X-API-Key": "alpha"}).status_code == 404
    # The API's description is not public either.
    for path in ("/docs", "/redoc", "/openapi.json"):
        assert httpx.get(f"{url}{path}").status_code == 401, path
        assert httpx.get(f"{url}{path}", headers={"X-API-Key": "gamma"}).status_code == 401, path
        assert httpx.get(f"{url}{path}", headers={"X-API-Key": "alpha"}).status_code == 200, path
    schema = httpx.get(f"{url}/openapi.json", headers={"Authorization": "Bearer beta"}).json()
    assert "/datasets" in schema["paths"] and "/openapi.json" not in schema["paths"]


def test_other_versions_shards_are_left_alone_and_frames_time_out(stack: Stack, services):
    """An API pinned to a version no worker runs: its dataset waits untouched and a frame request gets 503."""
    proc, url = stack.start_api({"SEASYNTH_WORKER_VERSION": "0.0.0-nobody", "SEASYNTH_FRAME_TIMEOUT_S": "1",
                                 "SEASYNTH_RETRY_AFTER_S": "7"})
    try:
        created = httpx.post(f"{url}/datasets", json=tiny_spec(frames=2, shard_size=1)).json()
        assert created["code_version"] == "0.0.0-nobody"
        r = httpx.get(f"{url}/datasets/{created['id']}/frames/0", timeout=30)
        assert r.status_code == 503 and r.headers["retry-after"] == "7", r.text
        rec = services.records.get(created["id"])
        assert (rec.state, rec.attempts, rec.renderer) == ("queued", 0, None)
    finally:
        proc.stop()


def test_a_frame_may_take_longer_than_five_seconds(stack: Stack):
    """The API waits frame_timeout_s for a frame worker, beyond redis-py's default 5 s socket timeout.

    The frames queue of an unserved version is answered by this test, playing a slow frame worker.
    """
    import base64
    import json
    import threading
    import time

    import redis

    from seasynth.service.queues import frame_queue
    from seasynth.service.records.store import push_reply

    version = "0.0.0-slowframes"
    proc, url = stack.start_api({"SEASYNTH_WORKER_VERSION": version, "SEASYNTH_FRAME_TIMEOUT_S": "20"})
    raw = redis.Redis.from_url(stack.settings().redis_url)
    try:
        dataset_id = httpx.post(f"{url}/datasets", json=tiny_spec(frames=2, shard_size=1)).json()["id"]
        got: dict = {}
        asked = time.monotonic()
        getter = threading.Thread(target=lambda: got.update(r=httpx.get(f"{url}/datasets/{dataset_id}/frames/1",
                                                                        timeout=40)))
        getter.start()
        _, message = raw.blpop([frame_queue(version)], timeout=10)
        body = json.loads(base64.b64decode(json.loads(message)["body"]))
        ds, index, part, reply_key = body[0]
        assert (ds, index, part) == (dataset_id, 1, "image")
        time.sleep(max(0.0, 6.5 - (time.monotonic() - asked)))
        push_reply(raw, reply_key, {"ok": True, "name": "image_2/000001.png"}, b"\x89PNG slow", ttl_s=60)
        getter.join(30)
        r = got["r"]
        assert r.status_code == 200, r.text
        assert r.content == b"\x89PNG slow" and time.monotonic() - asked >= 6.5
        httpx.delete(f"{url}/datasets/{dataset_id}")
    finally:
        raw.close()
        proc.stop()
