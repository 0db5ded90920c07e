"""Uploaded assets on a worker: each downloaded once per process from the object store and verified by its sha256."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from seasynth.service.errors import AssetError
from seasynth.service.shards import asset_info_key, asset_key
from seasynth.service.storage import ObjectStore


class AssetCache:
    """Maps an uploaded asset id to a local file: downloaded once per process, verified by its sha256."""

    def __init__(self, store: ObjectStore, folder: Path):
        self.store = store
        self.folder = Path(folder)

    def __call__(self, asset_id: str) -> Path:
        info = json.loads(self.store.get_bytes(asset_info_key(asset_id)))
        suffix = Path(info.get("filename", "")).suffix.lower()
        dest = self.folder / f"{asset_id}{suffix}"
        if dest.is_file():
            return dest
        self.folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".part-")
        os.close(fd)
        try:
            self.store.download(asset_key(asset_id), Path(tmp))
            digest = hashlib.sha256(Path(tmp).read_bytes()).hexdigest()
            if digest != asset_id:
                raise AssetError(f"asset {asset_id}: downloaded bytes have sha256 {digest}")
            os.replace(tmp, dest)
        finally:
            Path(tmp).unlink(missing_ok=True)
        return dest
