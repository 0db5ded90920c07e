"""Uploaded assets: checked, stored by content (assets/{sha256}) with a sidecar naming their format, listed, and
each mesh's picture for the playground (assets/thumbnails/{sha256}.png, drawn without OpenGL)."""

from __future__ import annotations

import hashlib
import json
import re
import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

from seasynth.api.deps import Services
from seasynth.api.uploads import FORMATS, MESH, FileFormat, format_of, validate
from seasynth.service.errors import AssetError, Conflict, LimitExceeded, NotFound
from seasynth.service.shards import asset_info_key, asset_key, asset_thumbnail_key

UPLOAD_SUFFIXES = tuple(FORMATS)
ASSET_ID = re.compile(r"^[0-9a-f]{64}$")
SIDECAR = re.compile(r"^assets/([0-9a-f]{64})\.json$")
NEVER = datetime.min.replace(tzinfo=UTC)


def stored_format(services: Services, asset_id: str) -> FileFormat | None:
    """The format an uploaded asset was stored as (its sidecar's file name), or None for no such asset."""
    info = _sidecar(services, asset_id)
    return None if info is None else format_of(info.get("filename", ""))


def _sidecar(services: Services, asset_id: str) -> dict[str, Any] | None:
    try:
        return json.loads(services.store.get_bytes(asset_info_key(asset_id)))
    except NotFound:
        return None


def store_asset(services: Services, filename: str, stream: BinaryIO) -> tuple[dict[str, Any], bool]:
    """Check and store an upload as assets/{sha256}; return its sidecar (with format and kind) and whether
    this upload created it.

    The upload is hashed into a temporary file and must load as its suffix says (AssetError, 422). The sidecar
    assets/{sha256}.json, whose file name tells workers the format, is written once: the first upload of some
    bytes decides their format for good. The same bytes again under the same format change nothing; under
    another format they are a Conflict (409) naming the stored one. A new mesh's picture is drawn in the same
    check and kept (or why it could not be: the mesh is stored all the same).
    """
    fmt = format_of(filename or "")
    if fmt is None:
        suffix = Path(filename or "").suffix.lower()
        what = (f"{filename!r} has the suffix {suffix!r}, which uploads do not take" if suffix else
                f"{filename!r} has no suffix" if filename else "the part has no file name")
        raise AssetError(f"file: {what}; the suffix sets the format: name it *{', *'.join(UPLOAD_SUFFIXES)}")
    limit = services.settings.max_asset_bytes
    sha, size = hashlib.sha256(), 0
    with tempfile.TemporaryDirectory(prefix="seasynth-upload-") as work, open(Path(work) / "upload", "w+b") as tmp:
        while chunk := stream.read(1 << 20):
            size += len(chunk)
            if size > limit:
                raise LimitExceeded(f"{filename}: over the limit of {limit} bytes (SEASYNTH_MAX_ASSET_BYTES)")
            sha.update(chunk)
            tmp.write(chunk)
        tmp.flush()
        if size == 0:
            raise AssetError(f"{filename}: the file is empty")
        asset_id = sha.hexdigest()
        stored, created, drawn = _sidecar(services, asset_id), False, None
        if stored is None:
            picture = Path(work) / "picture.png"
            drawn = (picture, validate(Path(tmp.name), fmt, filename, services.settings.upload_check_memory_mib,
                                       picture if fmt.kind == MESH else None))
            info = {"filename": Path(filename).name, "bytes": size, "sha256": asset_id, "format": fmt.format,
                    "kind": fmt.kind}
            # The sidecar goes first (an asset whose object exists always has its sidecar), and only if absent:
            # of two uploads racing with different formats one wins, and the other reads the winner's sidecar.
            created = services.store.put_bytes_if_absent(
                asset_info_key(asset_id), json.dumps(info).encode(), "application/json"
            )
            stored = info if created else _sidecar(services, asset_id)
        have = format_of(stored.get("filename", ""))
        if have != fmt:
            raise Conflict(f"{filename}: these bytes are already uploaded as asset {asset_id}, {have}, first as "
                           f"{stored.get('filename')!r}; they cannot also be {fmt}")
        # Also after a re-upload: an upload that died between the sidecar and the object left no object.
        if services.store.head(asset_key(asset_id)) is None:
            services.store.put_file(asset_key(asset_id), Path(tmp.name))
        if created and fmt.kind == MESH:
            _keep_thumbnail(services, asset_id, *drawn)
    return {**stored, "format": have.format, "kind": have.kind}, created


def list_assets(services: Services, offset: int, limit: int) -> tuple[list[dict[str, Any]], int]:
    """One page of the uploaded assets, newest first (by their sidecar's time: the first upload's), and how many
    there are: each sidecar with its format, kind and `uploaded_at` (None where the store keeps no time)."""
    sidecars = [o for o in services.store.list("assets/") if SIDECAR.fullmatch(o.key)]
    sidecars.sort(key=lambda o: (o.modified or NEVER, o.key), reverse=True)
    items = []
    for o in sidecars[offset:offset + limit]:
        asset_id = SIDECAR.fullmatch(o.key).group(1)
        info = _sidecar(services, asset_id)
        fmt = format_of((info or {}).get("filename", ""))
        if info is None or fmt is None:  # removed since the listing, or not written by this API
            continue
        items.append({**info, "sha256": asset_id, "format": fmt.format, "kind": fmt.kind, "uploaded_at": o.modified})
    return items, len(sidecars)


def thumbnail(services: Services, asset_id: str) -> bytes:
    """The PNG picture of uploaded mesh `asset_id`; NotFound for no such mesh, or naming why none could be drawn.

    Drawn at upload; a mesh uploaded before pictures were drawn gets its picture here, once (loaded in the upload
    check's child process, within its memory budget), and kept, as is the reason where it cannot be drawn."""
    info = _sidecar(services, asset_id) if ASSET_ID.fullmatch(asset_id) else None
    fmt = format_of((info or {}).get("filename", ""))
    if info is None or fmt is None:
        raise NotFound(f"no asset {asset_id[:80]!r}")
    if fmt.kind != MESH:
        raise NotFound(f"asset {asset_id} ({info['filename']}) is {fmt}: pictures are drawn for meshes")
    got = _kept_thumbnail(services, asset_id)
    if got is None:
        with tempfile.TemporaryDirectory(prefix="seasynth-thumbnail-") as work:
            mesh, picture = Path(work) / "mesh", Path(work) / "picture.png"
            services.store.download(asset_key(asset_id), mesh)  # NotFound: an upload that died before its object
            try:
                reason = validate(mesh, fmt, info["filename"], services.settings.upload_check_memory_mib, picture)
            except (AssetError, LimitExceeded) as err:  # as this API checks meshes now, or over today's budget
                reason = str(err)
            _keep_thumbnail(services, asset_id, picture, reason)
        got = _kept_thumbnail(services, asset_id)
    if isinstance(got, bytes):
        return got
    raise NotFound(f"asset {asset_id} ({info['filename']}): no picture could be drawn ({got})")


def _why_key(asset_id: str) -> str:
    return asset_thumbnail_key(asset_id).removesuffix(".png") + ".json"


def _keep_thumbnail(services: Services, asset_id: str, picture: Path, reason: str | None) -> None:
    """Store the drawn picture, or why there is none."""
    if reason is None and picture.is_file():
        services.store.put_file(asset_thumbnail_key(asset_id), picture, "image/png")
    else:
        why = json.dumps({"error": reason or "the check drew no picture"}).encode()
        services.store.put_bytes(_why_key(asset_id), why, "application/json")


def _kept_thumbnail(services: Services, asset_id: str) -> bytes | str | None:
    """The stored picture's bytes, or why none could be drawn, or None when neither is stored."""
    try:
        return services.store.get_bytes(asset_thumbnail_key(asset_id))
    except NotFound:
        pass
    try:
        return str(json.loads(services.store.get_bytes(_why_key(asset_id))).get("error"))
    except NotFound:
        return None
