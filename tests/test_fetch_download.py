"""How `seasynth fetch` downloads (seasynth.service.fetch), against a real HTTP server on loopback that serves byte ranges:
a download the network cuts off is continued with a Range request, in the same run or the next; the first failure
stops the other downloads at once; the assembled manifest.json carries no presigned URL; a reply that is not a
manifest is a clear error."""

from __future__ import annotations

import hashlib
import http.server
import io
import json
import tarfile
import threading
import time

import httpx
import pytest

from seasynth.service.errors import Unavailable
from seasynth.service.fetch import STATE_DIR, _download_all, _fetch, fetch_shard
from seasynth.service.fetch_manifest import get_manifest_page


class Store(http.server.ThreadingHTTPServer):
    """Objects by path. drops[path]: how many GETs of it are cut off halfway; slow: seconds per 64 KiB sent."""

    daemon_threads = True

    def __init__(self):
        super().__init__(("127.0.0.1", 0), Handler)
        self.objects: dict[str, tuple[bytes, str]] = {}
        self.drops: dict[str, int] = {}
        self.slow = 0.0
        self.log: list[tuple[str, str | None]] = []

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}{path}"


class Handler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args):
        pass

    def do_GET(self):
        store: Store = self.server
        path = self.path.split("?")[0]
        store.log.append((path, self.headers.get("Range")))
        if path not in store.objects:
            self.send_error(404)
            return
        body, kind = store.objects[path]
        start = int(self.headers["Range"].split("=")[1].rstrip("-")) if self.headers.get("Range") else 0
        self.send_response(206 if start else 200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body) - start))
        self.end_headers()
        rest = body[start:]
        if store.drops.get(path, 0) > 0:  # the network cuts this one off halfway
            store.drops[path] -= 1
            rest = rest[: len(rest) // 2]
        for k in range(0, len(rest), 1 << 16):
            self.wfile.write(rest[k:k + (1 << 16)])
            time.sleep(store.slow)
        self.wfile.flush()


@pytest.fixture
def store():
    s = Store()
    threading.Thread(target=s.serve_forever, daemon=True).start()
    yield s
    s.shutdown()
    s.server_close()


def shard_tar(index: int, size: int) -> bytes:
    """A shard tar whose image is `size` bytes of seeded noise (incompressible, so a cut-off is mid-file)."""
    data = hashlib.shake_256(str(index).encode()).digest(size)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        info = tarfile.TarInfo(f"image_2/{index:06d}.png")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def entry(store: Store, index: int, size: int = 3 << 20) -> dict:
    body = shard_tar(index, size)
    key = f"datasets/d/shards/shard-{index:06d}.tar"
    store.objects[f"/{key}"] = (body, "application/x-tar")
    return {"index": index, "key": key, "url": store.url(f"/{key}"), "sha256": hashlib.sha256(body).hexdigest(),
            "bytes": len(body)}


def test_a_download_the_network_cuts_off_is_continued_with_a_range_request(store, tmp_path):
    shard = entry(store, 0)
    store.drops[f"/{shard['key']}"] = 1
    counted = []
    with httpx.Client() as client:
        assert fetch_shard(client, shard, tmp_path / "out", counted.append) == (True, 1)
    (first, _), (again, ranged) = store.log
    assert first == again == f"/{shard['key']}" and ranged is not None and int(ranged[6:-1]) > 0
    assert sum(counted) == shard["bytes"]  # each byte counted once
    assert (tmp_path / "out/image_2/000000.png").read_bytes() == hashlib.shake_256(b"0").digest(3 << 20)
    assert [p.name for p in (tmp_path / "out" / STATE_DIR).iterdir()] == ["shard-000000.tar.done"]


def test_a_part_cut_off_on_every_attempt_is_kept_and_the_next_run_continues_it(store, tmp_path):
    shard = entry(store, 1)
    store.drops[f"/{shard['key']}"] = 3  # every attempt of this run
    part = tmp_path / "out" / STATE_DIR / "shard-000001.tar.part"
    with httpx.Client() as client:
        with pytest.raises(Unavailable, match=shard["key"]):
            fetch_shard(client, shard, tmp_path / "out", lambda n: None)
        assert 0 < part.stat().st_size < shard["bytes"]
        assert [r is None for _, r in store.log] == [True, False, False]  # each retry continued the part
        kept, counted = part.stat().st_size, []
        assert fetch_shard(client, shard, tmp_path / "out", counted.append) == (True, 1)
    assert store.log[-1][1] == f"bytes={kept}-" and sum(counted) == shard["bytes"]
    assert not part.exists()


def test_the_first_failure_stops_the_other_downloads(store, tmp_path):
    shards = [entry(store, i, 1 << 20) for i in range(8)]
    del store.objects[f"/{shards[0]['key']}"]  # 404 at once
    store.slow = 0.05  # 16 chunks: about 0.8 s a shard
    t0 = time.monotonic()
    with httpx.Client() as api:
        with pytest.raises(Unavailable, match="HTTP 404"):
            _download_all(api, store.url(""), "d", shards, tmp_path / "out", None, parallel=2, progress=False)
    assert time.monotonic() - t0 < 3.0  # not the 8 x 0.8 / 2 s the queue holds
    done = list((tmp_path / "out" / STATE_DIR).glob("*.done"))
    assert len(done) < 3, done
    requested = {p for p, _ in store.log}
    assert len(requested) <= 3, requested  # queued shards never started


def test_the_fetched_manifest_carries_no_presigned_url(store, tmp_path):
    shard = entry(store, 2, 1024)
    shard["exports"] = {"coco": {"key": "k", "sha256": "0" * 64, "bytes": 1, "url": store.url("/k?X-Amz-Signature=s")}}
    man = {"id": "d", "state": "succeeded", "complete": True, "shards_total": 1, "shards": [shard]}
    with httpx.Client() as api:
        _fetch(api, store.url(""), "d", man, tmp_path / "out", parallel=1, progress=False)
    text = (tmp_path / "out/manifest.json").read_text()
    assert "url" not in text and "Signature" not in text
    assert json.loads(text)["shards"][0]["exports"]["coco"] == {"key": "k", "sha256": "0" * 64, "bytes": 1}


@pytest.mark.parametrize("body, kind", [(b"<html>proxy login</html>", "text/html"), (b'{"status": "ok"}',
                                                                                        "application/json")])
def test_a_reply_that_is_not_a_manifest_page_is_a_clear_error(store, body, kind):
    store.objects["/datasets/d/manifest"] = (body, kind)
    with httpx.Client() as api:
        with pytest.raises(Unavailable, match=r"the manifest of d is not a seasynth manifest page .*is --api the API"):
            get_manifest_page(api, store.url("/datasets/d/manifest"), store.url(""), "d")


def manifest_body(shards: list[dict], **fields) -> bytes:
    return json.dumps({"id": "d", "state": "succeeded", "complete": True, "shards_total": len(shards),
                       "spec": {}, "next": None, **fields, "shards": shards}).encode()


def test_a_manifest_that_repeats_or_drops_shards_is_refused(store, tmp_path):
    from seasynth.service.fetch import IntegrityError, fetch_dataset

    a, b = entry(store, 0, 1024), entry(store, 1, 1024)
    for shards, total in (([a, a], 2), ([a], 2), ([b, a], 2)):
        store.objects["/datasets/d/manifest"] = (manifest_body(shards, shards_total=total), "application/json")
        with pytest.raises(IntegrityError, match="the manifest of d lists shards"):
            fetch_dataset(store.url(""), "d", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_a_dataset_that_will_not_complete_says_so(store, tmp_path):
    from seasynth.service.errors import Conflict
    from seasynth.service.fetch import fetch_dataset

    a = entry(store, 0, 1024)
    store.objects["/datasets/d/manifest"] = (manifest_body([a], state="failed", complete=False, shards_total=2),
                                             "application/json")
    with pytest.raises(Conflict, match=r"is failed with 1 of 2 shards committed; it will not complete \(pass "
                                       r"--partial"):
        fetch_dataset(store.url(""), "d", tmp_path / "out", progress=False)
