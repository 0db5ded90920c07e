"""Manifest pages over real HTTP with real Redis and moto's S3: pages by shard index with totals of the whole, and
`seasynth fetch` following them and asking again for URLs the store refuses."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
import threading

import httpx
from hardening import KEY, VERSION, api, commit, new_record, serve, services, settings  # noqa: F401 (fixtures)
from service_stack import tiny_spec

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
    from seasynth.service.fetch import fetch_dataset

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
    from seasynth.service.fetch import fetch_dataset

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
