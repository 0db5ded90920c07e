"""The API's security guarantees, against real components (redis-server, moto's S3, `seasynth serve` and a render
worker): keys compared in constant time, no secret in any log, Redis record or answer, presigned URLs of a bounded
and stated lifetime, spec asset references confined to uploaded assets, and decompression bombs refused with a
4xx in bounded memory. (The images' non-root users: tests/test_deploy.py.)"""

from __future__ import annotations

import gzip
import hmac
import json
import struct
import urllib.parse
import zlib

import httpx
import pytest
from isolated_stacks import api_on, isolated
from pydantic import ValidationError
from service_stack import Stack, tiny_spec, wait_state, wait_worker_ready

from seasynth.api.gate import api_key_ok
from seasynth.service.settings import Settings

KEY = "k-sec-3f9a1c77e2"  # distinctive: any occurrence in a log or record is this key
OTHER_KEY = "k-sec-second-51b0"
WRONG_KEY = "k-sec-wrong-0d4e"
AWS_SECRET = "aws-secret-7c2e91ab44"  # moto takes any credentials
PRESIGN_S = 900


# --- keys


@pytest.mark.parametrize("headers", [
    {"x-api-key": KEY}, {"x-api-key": OTHER_KEY}, {"authorization": f"Bearer {OTHER_KEY}"},
    {"x-api-key": WRONG_KEY}, {"x-api-key": WRONG_KEY, "authorization": f"bearer {KEY}"}, {}, {"x-api-key": " "},
], ids=["first", "second", "bearer", "wrong", "wrong-then-bearer", "none", "blank"])
def test_every_key_is_compared_in_constant_time_with_no_early_exit(monkeypatch, headers):
    """The same comparisons, each by hmac.compare_digest, whichever key matched, if any."""
    keys = frozenset({KEY, OTHER_KEY, "k-sec-third-77aa"})
    calls = []
    real = hmac.compare_digest

    def counted(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(hmac, "compare_digest", counted)
    ok = api_key_ok(headers, keys)
    assert ok is any(v.removeprefix("Bearer ").removeprefix("bearer ") in keys for v in headers.values())
    given = 1 + ("authorization" in headers)
    assert len(calls) == given * len(keys)  # every given value against every key, matched or not
    assert {b for _, b in calls} == {k.encode() for k in keys}


# --- secrets, presigned URLs


def _redis_values(raw) -> bytes:
    """Every key and value in the Redis database, as bytes."""
    out = []
    for key in raw.scan_iter(count=1000):
        kind = raw.type(key).decode()
        out.append(key)
        if kind == "string":
            out.append(raw.get(key) or b"")
        elif kind == "hash":
            out += [x for kv in raw.hgetall(key).items() for x in kv]
        elif kind == "list":
            out += raw.lrange(key, 0, -1)
        elif kind == "set":
            out += list(raw.smembers(key))
        elif kind == "zset":
            out += raw.zrange(key, 0, -1)
    return b"\n".join(out)


def test_no_secret_in_logs_records_or_answers_and_presigned_urls_are_bounded(infra: Stack):
    """A dataset rendered through a keyed API by a worker holding the AWS secret: neither key, nor a refused one,
    nor the secret appears in the API's or the worker's log, in Redis or in any answer; the manifest states the
    URLs' lifetime, which each URL carries."""
    with isolated(infra, 7, api_keys=f"{KEY},{OTHER_KEY}", presign_expiry_s=PRESIGN_S) as (env, services):
        env = {**env, "AWS_SECRET_ACCESS_KEY": AWS_SECRET}
        worker = infra.seasynth("worker-secrets", "worker", "--concurrency", "1", "--loglevel", "DEBUG", env=env)
        api, url = infra.start_api(env)
        bodies = []
        try:
            wait_worker_ready(worker, 1)
            assert httpx.get(f"{url}/datasets", headers={"X-API-Key": WRONG_KEY}).status_code == 401
            assert httpx.get(f"{url}/datasets", headers={"Authorization": f"Bearer {WRONG_KEY}"}).status_code == 401
            with httpx.Client(base_url=url, headers={"X-API-Key": KEY}, timeout=30) as client:
                r = client.post("/datasets", json=tiny_spec(frames=4, shard_size=2))
                assert r.status_code == 202, r.text
                dataset_id = r.json()["id"]
                bodies.append(r.text)
                bodies.append(json.dumps(wait_state(client, dataset_id, {"succeeded"})))
                manifest = client.get(f"/datasets/{dataset_id}/manifest")
                bodies += [manifest.text, client.get("/datasets").text, client.get("/metrics").text]
            page = manifest.json()
            assert page["urls_expire_s"] == PRESIGN_S
            urls = [s["url"] for s in page["shards"]]
            assert len(urls) == 2
            for u in urls:
                query = urllib.parse.parse_qs(urllib.parse.urlsplit(u).query)
                assert query["X-Amz-Expires"] == [str(PRESIGN_S)]
                assert httpx.get(u).status_code == 200
        finally:
            api.stop()
            worker.stop()
        texts = {"api log": api.log.read_bytes(), "worker log": worker.log.read_bytes(),
                 "redis": _redis_values(services.raw_redis), "answers": "\n".join(bodies).encode()}
        assert b"render session ready" in texts["worker log"] and b'"POST /datasets HTTP/1.1" 202' in texts["api log"]
        for secret in (KEY, OTHER_KEY, WRONG_KEY, AWS_SECRET):
            found = [where for where, text in texts.items() if secret.encode() in text]
            assert found == [], f"{secret!r} appears in {found}"


@pytest.mark.parametrize("value", [59, 7 * 24 * 3600 + 1])
def test_presigned_url_lifetime_is_bounded(value):
    with pytest.raises(ValidationError) as err:
        Settings(presign_expiry_s=value)
    assert err.value.errors()[0]["loc"] == ("presign_expiry_s",)


# --- asset references


HOSTILE_PATHS = ["../../etc/passwd", "/etc/passwd", "..\\..\\windows\\win.ini", "http://169.254.169.254/latest",
                 "s3://another-bucket/mesh.glb", "file:///etc/passwd", "assets/../../../x.glb"]
HOSTILE_IDS = ["../" + "a" * 61, "a" * 64 + "/../x", "A" * 64, "a" * 63, "/" + "a" * 63, "a" * 32 + "%2e%2e" + "a" * 26]
FIELDS = {  # where a spec names a file -> the spec change that puts `ref` there
    "targets.assets.0": lambda ref: {"targets": {"count": [1, 2], "assets": [ref]}},
    "distractors.assets.0": lambda ref: {"distractors": {"count": [1, 2], "assets": [ref]}},
    "terrain.mesh": lambda ref: {"terrain": {"cells": 16, "variants": 1, "mesh": ref}},
    "terrain.texture": lambda ref: {"terrain": {"cells": 16, "variants": 1, "texture": ref}},
}


@pytest.fixture(scope="module")
def api(infra: Stack):
    with isolated(infra, 5, api_keys=KEY) as (_, services), api_on(services) as client:
        client.headers["X-API-Key"] = KEY
        yield client, services


@pytest.mark.parametrize("field", sorted(FIELDS))
def test_hostile_asset_references_are_refused_naming_the_field(api, field):
    """Paths (traversal, absolute, URLs of any scheme) and asset ids that are not 64 lowercase hex digits: 422
    naming the field, and no dataset created or queued."""
    client, services = api
    for source, values in (("path", HOSTILE_PATHS), ("asset_id", HOSTILE_IDS)):
        for value in values:
            r = client.post("/datasets", json=tiny_spec(**FIELDS[field]({source: value})))
            assert r.status_code == 422, (field, value, r.text)
            assert any(e.startswith(f"{field}.{source}:") for e in r.json()["errors"]), (field, value, r.json())
    assert client.get("/datasets").json()["total"] == 0
    assert services.raw_redis.keys("seasynth.*") == []  # nothing published


# --- decompression bombs


def _png(width: int, height: int, extra: bytes = b"", idat: bytes | None = None) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)  # 8-bit greyscale
    idat = idat if idat is not None else zlib.compress(b"\0" * (height * (width + 1)))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + extra + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _zeros_deflated(size: int) -> bytes:
    """`size` zero bytes, zlib-compressed a MiB at a time (about 1/1000 of the size)."""
    z = zlib.compressobj(9)
    return b"".join([z.compress(b"\0" * 2**20) for _ in range(size // 2**20)] + [z.flush()])


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _peak_rss_mib(pid: int) -> float:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


BOMB = 128 * 2**20  # inflated bytes of each bomb below, in about 130 KB
BOMBS = [  # name, file, what the 422 says (None: the file is fine as far as its pixels go)
    ("header.png", lambda: _png(100_000, 100_000, idat=zlib.compress(b"\0" * 1000)), "pixels"),
    ("huge.png", lambda: _png(9000, 8000, idat=zlib.compress(b"\0" * 1000)), "9000x8000 pixels is over the limit"),
    ("ztxt.png", lambda: _png(4, 4, extra=_chunk(b"zTXt", b"Comment\0\0" + _zeros_deflated(BOMB))),
     "Decompressed data too large"),
    ("iccp.png", lambda: _png(4, 4, extra=_chunk(b"iCCP", b"icc\0\0" + _zeros_deflated(BOMB))),
     "Decompressed data too large"),
    # Image data that inflates far past its 4x4 pixels: decoding stops at the last pixel (a valid upload).
    ("idat.png", lambda: _png(4, 4, idat=_zeros_deflated(BOMB)), None),
]


def test_decompression_bombs_are_refused_in_bounded_memory(infra: Stack):
    """PNGs of a few hundred KB that declare 10^10 or 7.2 * 10^7 pixels, or inflate to 128 MiB in a text or
    colour-profile chunk: 422 naming the upload. Image data that inflates past its pixels is read only as far as
    they go. Over all of them, the API process's peak memory grows by less than 64 MiB."""
    with isolated(infra, 7, api_keys=KEY, max_asset_bytes=16 * 2**20) as (env, _):
        api, url = infra.start_api(env)
        try:
            pid = api.popen.pid
            with httpx.Client(base_url=url, headers={"X-API-Key": KEY}, timeout=60) as client:
                assert client.post("/assets", files={"file": ("ok.png", _png(8, 8))}).status_code == 201
                before = _peak_rss_mib(pid)
                for name, make, error in BOMBS:
                    data = make()
                    assert len(data) < 16 * 2**20
                    r = client.post("/assets", files={"file": (name, data)})
                    if error is None:
                        assert r.status_code == 201 and r.json()["bytes"] == len(data), (name, r.text)
                        continue
                    assert r.status_code == 422, (name, r.text)
                    (line,) = r.json()["errors"]
                    assert line.startswith(f"{name}: ") and error in line, line
                grown = _peak_rss_mib(pid) - before
            assert grown < 64, f"peak RSS grew by {grown:.0f} MiB"
        finally:
            api.stop()


def test_compressed_request_bodies_are_not_inflated(api):
    """No request body is decompressed: a gzip-encoded spec is read as the bytes it is (not JSON: 400), so the
    body limit counts what is inflated, too."""
    client, _ = api
    body = gzip.compress(json.dumps(tiny_spec()).encode())
    r = client.post("/datasets", content=body,
                    headers={"Content-Type": "application/json", "Content-Encoding": "gzip"})
    assert (r.status_code, r.json()["detail"]) == (400, "There was an error parsing the body"), r.text
    assert client.get("/datasets").json()["total"] == 0
