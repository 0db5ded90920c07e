"""`seasynth fetch`: download a dataset's shards in parallel, verify sha256, resume, assemble one KITTI tree."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tarfile
import urllib.parse
import urllib.request
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.errors import Conflict, NotFound, OutputError, SeasynthError, Unauthorized, Unavailable

STATE_DIR = ".seasynth-fetch"  # per-shard .part downloads and .done markers; resume reads it
ATTEMPTS = 3


class IntegrityError(SeasynthError):
    """A downloaded shard whose sha256 or size differs from the manifest's."""


class Expired(Unavailable):
    """The object store refused a shard's URL (HTTP 403): a presigned URL that expired, which a fresh one cures."""


@dataclass(frozen=True)
class FetchReport:
    shards_total: int
    shards_fetched: int
    shards_skipped: int
    bytes_downloaded: int
    files: int


# Fields of one manifest page that say which page it is; the assembled manifest drops them.
PAGE_FIELDS = ("start", "limit", "next")
MAX_PAGES = 1_000_000  # a guard against a server whose `next` links never end


def manifest_url(api_url: str, dataset_id: str) -> str:
    return f"{api_url.rstrip('/')}/datasets/{urllib.parse.quote(dataset_id, safe='')}/manifest"


def get_manifest(client, api_url: str, dataset_id: str) -> dict[str, Any]:
    """The whole manifest: every page's shards, following `next` links, under the first page's other fields."""
    base = api_url.rstrip("/")
    man = get_manifest_page(client, manifest_url(api_url, dataset_id), api_url, dataset_id)
    shards, nxt, pages = list(man["shards"]), man.get("next"), 1
    while nxt:
        if pages >= MAX_PAGES:
            raise Unavailable(f"{api_url}: manifest of {dataset_id} has over {MAX_PAGES} pages")
        page = get_manifest_page(client, urllib.parse.urljoin(base + "/", nxt.lstrip("/")), api_url, dataset_id)
        shards += page["shards"]
        nxt, pages = page.get("next"), pages + 1
    out = {k: v for k, v in man.items() if k not in PAGE_FIELDS}
    out["shards"] = shards
    return out


def get_manifest_page(client, url: str, api_url: str, dataset_id: str) -> dict[str, Any]:
    import httpx

    try:
        r = client.get(url)
    except httpx.HTTPError as err:
        raise Unavailable(f"{api_url}: cannot reach the API ({err})") from err
    if r.status_code == 404:
        raise NotFound(f"no dataset {dataset_id} at {api_url} ({_detail(r)})")
    if r.status_code == 401:
        raise Unauthorized(f"{api_url}: an API key is needed (--api-key or SEASYNTH_API_KEY)")
    if r.status_code >= 400:
        raise Unavailable(f"{api_url}: manifest of {dataset_id} failed with HTTP {r.status_code}: {_detail(r)}")
    return r.json()


def url_refresher(client, api_url: str, dataset_id: str) -> Callable[[dict[str, Any]], str]:
    """refresh(shard) -> a new URL for a manifest shard, from the one-shard manifest page at its index."""

    def refresh(shard: dict[str, Any]) -> str:
        url = f"{manifest_url(api_url, dataset_id)}?start={shard['index']}&limit=1"
        for s in get_manifest_page(client, url, api_url, dataset_id)["shards"]:
            if s["index"] == shard["index"] and s["sha256"] == shard["sha256"]:
                return s["url"]
        raise Unavailable(f"{shard['key']}: no longer in the manifest of {dataset_id} at {api_url}")

    return refresh


def _detail(r) -> str:
    try:
        return str(r.json().get("detail", r.text))
    except ValueError:
        return r.text[:200]


def _safe_member(name: str) -> str:
    parts = name.split("/")
    if not name or name.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise IntegrityError(f"shard member {name!r} is not a plain relative path")
    return name


def download(client, url: str, part: Path, on_bytes: Callable[[int], None]) -> None:
    """Download `url` to `part`, continuing a partial file with an HTTP Range request."""
    if url.startswith("file://"):  # a local object store
        src = Path(urllib.request.url2pathname(urllib.parse.urlparse(url).path))
        shutil.copyfile(src, part)
        on_bytes(part.stat().st_size)
        return
    have = part.stat().st_size if part.exists() else 0
    headers = {"Range": f"bytes={have}-"} if have else {}
    with client.stream("GET", url, headers=headers) as r:
        if r.status_code == 416:  # already whole
            return
        if r.status_code == 403:
            raise Expired(f"GET {url.split('?')[0]}: HTTP 403 (a presigned URL that expired?)")
        if r.status_code not in (200, 206):
            raise Unavailable(f"GET {url.split('?')[0]}: HTTP {r.status_code}")
        mode = "ab" if r.status_code == 206 else "wb"
        if mode == "wb" and have:
            on_bytes(-have)
        with open(part, mode) as f:
            for chunk in r.iter_bytes(1 << 20):
                f.write(chunk)
                on_bytes(len(chunk))


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def extract(tar_path: Path, out: Path) -> int:
    """Write every member into `out` (each file written whole, then renamed); return the file count."""
    n = 0
    with tarfile.open(tar_path, "r:*") as tar:
        for m in tar:
            name = _safe_member(m.name)
            if not m.isfile():
                raise IntegrityError(f"{tar_path.name}: member {name!r} is not a regular file")
            dest = out / name
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp = dest.with_name(f".{dest.name}.part")
            with tar.extractfile(m) as src, open(tmp, "wb") as f:
                shutil.copyfileobj(src, f)
            os.replace(tmp, dest)
            n += 1
    return n


def fetch_shard(
    client,
    shard: dict[str, Any],
    out: Path,
    on_bytes: Callable[[int], None],
    refresh: Callable[[dict[str, Any]], str] | None = None,
) -> tuple[bool, int]:
    """Fetch, verify and extract one shard unless its .done marker says so; return (fetched, files).

    refresh(shard): a new URL for the shard, asked for when the store refuses its URL (presigned URLs expire, and
    a long download can outlast them); the part already downloaded is kept and continued.
    """
    import httpx

    state = out / STATE_DIR
    name = Path(shard["key"]).name
    done = state / f"{name}.done"
    if done.exists() and done.read_text().strip() == shard["sha256"]:
        on_bytes(shard["bytes"])
        return False, 0
    part = state / f"{name}.part"
    for attempt in range(1, ATTEMPTS + 1):
        try:
            download(client, shard["url"], part, on_bytes)
            size, digest = part.stat().st_size, sha256_file(part)
            if size != shard["bytes"] or digest != shard["sha256"]:
                raise IntegrityError(
                    f"{shard['key']}: got {size} bytes with sha256 {digest}, manifest says "
                    f"{shard['bytes']} bytes with sha256 {shard['sha256']}"
                )
            break
        except Expired:
            if refresh is None or attempt == ATTEMPTS:
                raise
            shard = {**shard, "url": refresh(shard)}
        except (IntegrityError, Unavailable, OSError, httpx.HTTPError) as err:
            on_bytes(-(part.stat().st_size if part.exists() else 0))
            part.unlink(missing_ok=True)  # a bad or stale part never gets resumed
            if attempt == ATTEMPTS:
                raise err if isinstance(err, SeasynthError) else Unavailable(f"{shard['key']}: {err}") from err
    files = extract(part, out)
    done.write_text(shard["sha256"] + "\n")
    part.unlink()
    return True, files


def fetch_dataset(
    api_url: str,
    dataset_id: str,
    out: Path,
    *,
    api_key: str | None = None,
    parallel: int = 4,
    partial: bool = False,
    progress: bool = True,
) -> FetchReport:
    """Fetch a finished dataset (or, with partial, the shards committed so far) into `out`."""
    import httpx

    headers = {"X-API-Key": api_key} if api_key else {}
    with httpx.Client(headers=headers, timeout=httpx.Timeout(60.0, connect=10.0), follow_redirects=True) as api:
        return _fetch(api, api_url, dataset_id, Path(out), parallel=parallel, partial=partial, progress=progress)


def _fetch(api, api_url: str, dataset_id: str, out: Path, *, parallel: int, partial: bool, progress: bool
           ) -> FetchReport:
    """fetch_dataset with its API client (kept open: expired shard URLs are asked for again)."""
    import httpx

    man = get_manifest(api, api_url, dataset_id)
    if not man["complete"] and not partial:
        raise Conflict(
            f"dataset {dataset_id} is {man['state']} with {len(man['shards'])} of {man['shards_total']} shards "
            "committed; wait for it to finish or pass --partial"
        )
    try:
        (out / STATE_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{out}: cannot create the output folder ({err.strerror or err})") from err
    shards = man["shards"]
    total_bytes = sum(s["bytes"] for s in shards)
    fetched = skipped = files = 0
    bar = _Bar(total_bytes, f"{dataset_id[:8]}: {len(shards)} shards", progress)
    # Presigned URLs carry their own authorisation: no API key goes to the object store.
    with bar, httpx.Client(timeout=httpx.Timeout(120.0, connect=10.0)) as storage:
        with ThreadPoolExecutor(max_workers=max(1, parallel)) as pool:
            refresh = url_refresher(api, api_url, dataset_id)
            futures = [pool.submit(fetch_shard, storage, s, out, bar.advance, refresh) for s in shards]
            for fut in as_completed(futures):
                got, n = fut.result()
                fetched += got
                skipped += not got
                files += n
    public = {k: v for k, v in man.items() if k != "shards"}
    public["shards"] = [{k: v for k, v in s.items() if k != "url"} for s in shards]
    (out / "manifest.json").write_text(json.dumps(public, indent=1, sort_keys=True) + "\n")
    return FetchReport(len(shards), fetched, skipped, bar.downloaded, files)


class _Bar:
    """A rich progress bar over bytes (thread-safe advance), or nothing."""

    def __init__(self, total: int, label: str, enabled: bool):
        import threading

        self._lock = threading.Lock()
        self.downloaded = 0
        self._progress = None
        if enabled:
            from rich.progress import (
                BarColumn,
                DownloadColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
                TransferSpeedColumn,
            )

            self._progress = Progress(
                TextColumn(label), BarColumn(), DownloadColumn(), TransferSpeedColumn(), TimeRemainingColumn()
            )
            self._task = self._progress.add_task("fetch", total=total)

    def advance(self, n: int) -> None:
        with self._lock:
            self.downloaded += n
            if self._progress is not None:
                self._progress.advance(self._task, n)

    def __enter__(self) -> _Bar:
        if self._progress is not None:
            self._progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.stop()
