"""`seasynth fetch`: download a dataset's shards in parallel, verify sha256, resume, assemble one KITTI tree (or
merge the shards' parts of an export format into one export)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tarfile
import threading
import urllib.parse
import urllib.request
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from seasynth.service.errors import Conflict, OutputError, SeasynthError, Unavailable
from seasynth.service.fetch_manifest import get_manifest, url_refresher
from seasynth.service.files import write_atomic

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


def _safe_member(name: str, key: str) -> str:
    """A tar member's name, if it is a plain relative path outside the fetch's own files."""
    parts = name.split("/")
    if not name or name.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise IntegrityError(f"{key}: member {name!r} is not a plain relative path")
    if parts[0] in (STATE_DIR, "manifest.json"):
        raise IntegrityError(f"{key}: member {name!r} would overwrite the fetch's own {parts[0]}")
    return name


class Stopped(Exception):
    """A download stopped because another one failed or the fetch was interrupted; its part file is kept."""


def download(client, url: str, part: Path, on_bytes: Callable[[int], None], stop=None) -> None:
    """Download `url` to `part`, continuing a partial file with an HTTP Range request. stop: a threading.Event
    that, once set, ends the download after its current chunk (Stopped), the part kept for the next run."""
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
                if stop is not None and stop.is_set():
                    raise Stopped(url.split("?")[0])


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def extract(tar_path: Path, out: Path, key: str | None = None) -> int:
    """Write every member into `out` (each file written whole, then renamed); return the file count. key: the
    shard's, for errors (default: the tar's file name)."""
    key = key or tar_path.name
    n = 0
    with tarfile.open(tar_path, "r:*") as tar:
        for m in tar:
            name = _safe_member(m.name, key)
            if not m.isfile():
                raise IntegrityError(f"{key}: member {name!r} is not a regular file")
            dest = out / name
            tmp = dest.with_name(f".{dest.name}.part")
            try:
                dest.parent.mkdir(parents=True, exist_ok=True)
                with tar.extractfile(m) as src, open(tmp, "wb") as f:
                    shutil.copyfileobj(src, f)
                os.replace(tmp, dest)
            except OSError as err:
                with contextlib.suppress(OSError):
                    tmp.unlink(missing_ok=True)
                raise OutputError(f"{dest}: cannot write {name} of {key} ({err.strerror or err})") from None
            n += 1
    return n


def fetch_shard(
    client,
    shard: dict[str, Any],
    out: Path,
    on_bytes: Callable[[int], None],
    refresh: Callable[[dict[str, Any]], str] | None = None,
    state: Path | None = None,
    replace: bool = False,
    stop=None,
) -> tuple[bool, int]:
    """Fetch, verify and extract one shard (or export part: any object with index, key, url, sha256 and bytes)
    into `out` unless its .done marker says so; return (fetched, files).

    refresh(shard): a new URL for the shard, asked for when the store refuses its URL (presigned URLs expire, and
    a long download can outlast them); the part already downloaded is kept and continued. state: the folder of
    its .part download and .done marker (default out/STATE_DIR). replace: `out` is this object's alone: what an
    earlier object left there is removed before extracting. stop: see download.

    A part that failed its sha256 or size is deleted; one cut off by the network, a 5xx or a full disk is kept, and
    the next attempt (or run) continues it with a Range request.
    """
    import httpx

    state = out / STATE_DIR if state is None else state
    state.mkdir(parents=True, exist_ok=True)
    name = Path(shard["key"]).name
    done = state / f"{name}.done"
    if done.exists() and done.read_text().strip() == shard["sha256"]:
        on_bytes(shard["bytes"])
        return False, 0
    part = state / f"{name}.part"
    if part.exists():  # an earlier run's, which download continues: its bytes count as downloaded
        on_bytes(part.stat().st_size)
    for attempt in range(1, ATTEMPTS + 1):
        try:
            download(client, shard["url"], part, on_bytes, stop)
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
            if isinstance(err, IntegrityError):  # a bad part is never resumed
                on_bytes(-(part.stat().st_size if part.exists() else 0))
                part.unlink(missing_ok=True)
            if attempt == ATTEMPTS:
                raise err if isinstance(err, SeasynthError) else Unavailable(f"{shard['key']}: {err}") from err
    if replace:
        shutil.rmtree(out, ignore_errors=True)
    files = extract(part, out, shard["key"])
    write_atomic(done, (shard["sha256"] + "\n").encode())
    part.unlink()
    return True, files


class ExportMerger(Protocol):
    """Turns the fetched export parts of one format into one export folder (worker.export.merge.PartMerger; the
    CLI passes it, so this module imports no worker code)."""

    format: str

    def prepare(self, out: Path) -> None:
        """Check `out` may receive the export (before anything is downloaded) and mark it unfinished."""
        ...

    def merge(self, manifest: dict[str, Any], parts: list[tuple[dict[str, Any], Path]], out: Path) -> int:
        """Merge (shard entry, folder its part was extracted into) in shard order into `out`; files written."""
        ...


def fetch_dataset(
    api_url: str,
    dataset_id: str,
    out: Path,
    *,
    api_key: str | None = None,
    parallel: int = 4,
    partial: bool = False,
    progress: bool = True,
    merger: ExportMerger | None = None,
) -> FetchReport:
    """Fetch a finished dataset (or, with partial, the shards committed so far) into `out`: its KITTI tree, or
    with `merger`, the shards' parts of that export format merged into one export (see fetch_export)."""
    import httpx

    headers = {"X-API-Key": api_key} if api_key else {}
    with httpx.Client(headers=headers, timeout=httpx.Timeout(60.0, connect=10.0), follow_redirects=True) as api:
        man = get_manifest(api, api_url, dataset_id)
        indices = [s["index"] for s in man["shards"]]
        if indices != sorted(set(indices)) or (man["complete"] and len(indices) != man["shards_total"]):
            raise IntegrityError(f"{api_url}: the manifest of {dataset_id} lists shards {len(indices)} times for "
                                 f"{len(set(indices))} shards of {man['shards_total']} (complete: {man['complete']}); "
                                 "a proxy or server that repeats or drops pages?")
        if not man["complete"] and not partial:
            hint = ("it will not complete (pass --partial to fetch the committed ones)"
                    if man["state"] in ("failed", "cancelled") else "wait for it to finish or pass --partial")
            raise Conflict(f"dataset {dataset_id} is {man['state']} with {len(man['shards'])} of {man['shards_total']} "
                           f"shards committed; {hint}")
        if merger is not None:
            return fetch_export(api, api_url, dataset_id, man, Path(out), merger, parallel=parallel,
                                progress=progress)
        return _fetch(api, api_url, dataset_id, man, Path(out), parallel=parallel, progress=progress)


def _fetch(api, api_url: str, dataset_id: str, man: dict[str, Any], out: Path, *, parallel: int, progress: bool
           ) -> FetchReport:
    """The KITTI tree, with its API client (kept open: expired shard URLs are asked for again)."""
    _make_state(out / STATE_DIR)
    shards = man["shards"]
    fetched, skipped, files, downloaded = _download_all(api, api_url, dataset_id, shards, out, None,
                                                        parallel=parallel, progress=progress)
    public = {k: v for k, v in man.items() if k != "shards"}
    public["shards"] = [_without_urls(s) for s in shards]
    write_atomic(out / "manifest.json", (json.dumps(public, indent=1, sort_keys=True) + "\n").encode())
    return FetchReport(len(shards), fetched, skipped, downloaded, files)


def fetch_export(api, api_url: str, dataset_id: str, man: dict[str, Any], out: Path, merger: ExportMerger, *,
                 parallel: int, progress: bool) -> FetchReport:
    """The shards' parts of export format merger.format, each verified by the manifest's sha256 and size and
    extracted into out/STATE_DIR/{format}/shard-{index}/, then merged into `out` (no KITTI files, no manifest.json:
    the export's record names the dataset). A dataset generated without outputs.{format} is refused before anything
    is downloaded. The extracted parts stay (hard links of the export's files where the filesystem allows), so a
    second run downloads nothing and merges again."""
    fmt = merger.format
    outputs = man["spec"].get("outputs") or {}
    if not outputs.get(fmt):
        raise Conflict(f"dataset {dataset_id} was generated without outputs.{fmt}, so its shards have no {fmt} "
                       f"parts; fetch its KITTI tree (no --format) and convert it with `seasynth export DIR --format "
                       f"{fmt} --out OUT`, or create the dataset again with outputs.{fmt}: true")
    parts = []
    for s in man["shards"]:
        part = (s.get("exports") or {}).get(fmt)
        if part is None:
            raise IntegrityError(f"{s['key']}: the manifest of {dataset_id} lists no {fmt} part for shard "
                                 f"{s['index']}, though its spec has outputs.{fmt}")
        parts.append({**part, "index": s["index"]})
    merger.prepare(out)
    state = out / STATE_DIR / fmt
    _make_state(state)
    fetched, skipped, _, downloaded = _download_all(api, api_url, dataset_id, parts, out, fmt, parallel=parallel,
                                                    progress=progress)
    files = merger.merge(man, [(s, state / _part_folder(s)) for s in man["shards"]], out)
    return FetchReport(len(parts), fetched, skipped, downloaded, files)


def _without_urls(shard: dict[str, Any]) -> dict[str, Any]:
    """A manifest shard without its presigned URLs (its own and its export parts'): they expire, and let whoever
    holds a copy of the dataset read the bucket until then."""
    out = {k: v for k, v in shard.items() if k != "url"}
    if out.get("exports"):
        out["exports"] = {fmt: {k: v for k, v in part.items() if k != "url"} for fmt, part in out["exports"].items()}
    return out


def _part_folder(shard: dict[str, Any]) -> str:
    return f"shard-{shard['index']:06d}"


def _make_state(state: Path) -> None:
    try:
        state.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{state}: cannot create the output folder ({err.strerror or err})") from err


def _download_all(api, api_url: str, dataset_id: str, objects: list[dict[str, Any]], out: Path, fmt: str | None, *,
                  parallel: int, progress: bool) -> tuple[int, int, int, int]:
    """Fetch every shard (fmt None: into `out`) or export part (into out/STATE_DIR/{fmt}/shard-{index}/) in
    parallel; (fetched, skipped, files, bytes downloaded)."""
    import httpx

    fetched = skipped = files = 0
    what = "shards" if fmt is None else f"{fmt} parts"
    bar = _Bar(sum(s["bytes"] for s in objects), f"{dataset_id[:8]}: {len(objects)} {what}", progress)
    state = None if fmt is None else out / STATE_DIR / fmt
    # Presigned URLs carry their own authorisation: no API key goes to the object store.
    # The first failure (or Ctrl-C, SIGTERM) stops the rest: queued shards never start, running downloads end
    # after their current chunk with their part kept, so the next run continues them.
    stop = threading.Event()
    with bar, httpx.Client(timeout=httpx.Timeout(120.0, connect=10.0)) as storage:
        with ThreadPoolExecutor(max_workers=max(1, parallel)) as pool:
            refresh = url_refresher(api, api_url, dataset_id, fmt)
            futures = [pool.submit(fetch_shard, storage, s, out if state is None else state / _part_folder(s),
                                   bar.advance, refresh, state, state is not None, stop) for s in objects]
            try:
                for fut in as_completed(futures):
                    got, n = fut.result()
                    fetched += got
                    skipped += not got
                    files += n
            except BaseException:
                stop.set()
                for f in futures:
                    f.cancel()
                raise
    return fetched, skipped, files, bar.downloaded


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
