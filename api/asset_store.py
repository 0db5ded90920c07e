"""Uploaded assets: checked, stored by content (assets/{sha256}) with a sidecar naming their format."""

from __future__ import annotations

import hashlib
import json
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

from seasynth.api.deps import Services
from seasynth.api.uploads import FORMATS, FileFormat, format_of, validate
from seasynth.service.errors import AssetError, Conflict, LimitExceeded, NotFound
from seasynth.service.shards import asset_info_key, asset_key

UPLOAD_SUFFIXES = tuple(FORMATS)


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
    another format they are a Conflict (409) naming the stored one.
    """
    fmt = format_of(filename or "")
    if fmt is None:
        suffix = Path(filename or "").suffix.lower()
        what = (f"{filename!r} has the suffix {suffix!r}, which uploads do not take" if suffix else
                f"{filename!r} has no suffix" if filename else "the part has no file name")
        raise AssetError(f"file: {what}; the suffix sets the format: name it *{', *'.join(UPLOAD_SUFFIXES)}")
    limit = services.settings.max_asset_bytes
    sha, size = hashlib.sha256(), 0
    with tempfile.NamedTemporaryFile(prefix="seasynth-upload-") as tmp:
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
        stored, created = _sidecar(services, asset_id), False
        if stored is None:
            validate(Path(tmp.name), fmt, filename, services.settings.upload_check_memory_mib)
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
    return {**stored, "format": have.format, "kind": have.kind}, created
