"""The manifest side of `seasynth fetch`: the dataset's manifest over HTTP, page by page (following `next` links),
and fresh URLs for shards whose presigned URLs expired. Errors name the API and the dataset."""

from __future__ import annotations

import urllib.parse
from collections.abc import Callable
from typing import Any

from seasynth.service.errors import NotFound, Unauthorized, Unavailable

# Fields of one manifest page that say which page it is, or how long its urls last; the assembled manifest drops them.
PAGE_FIELDS = ("start", "limit", "next", "urls_expire_s")
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
    try:
        page = r.json()
    except ValueError:
        page = None
    if not isinstance(page, dict) or not isinstance(page.get("shards"), list):
        raise Unavailable(f"{api_url}: the manifest of {dataset_id} is not a seasynth manifest page (HTTP "
                          f"{r.status_code}, {r.headers.get('content-type', 'no content type')}): is --api the API?")
    return page


def url_refresher(client, api_url: str, dataset_id: str, fmt: str | None = None) -> Callable[[dict[str, Any]], str]:
    """refresh(shard) -> a new URL for a manifest shard (or its part of export format `fmt`), from the one-shard
    manifest page at its index."""

    def refresh(shard: dict[str, Any]) -> str:
        url = f"{manifest_url(api_url, dataset_id)}?start={shard['index']}&limit=1"
        for s in get_manifest_page(client, url, api_url, dataset_id)["shards"]:
            entry = s if fmt is None else (s.get("exports") or {}).get(fmt, {})
            if s["index"] == shard["index"] and entry.get("sha256") == shard["sha256"]:
                return entry["url"]
        raise Unavailable(f"{shard['key']}: no longer in the manifest of {dataset_id} at {api_url}")

    return refresh


def _detail(r) -> str:
    try:
        return str(r.json().get("detail", r.text))
    except ValueError:
        return r.text[:200]
