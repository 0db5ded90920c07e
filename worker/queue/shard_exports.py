"""A shard's export parts in the bucket: its frames kept on disk while the KITTI tar is packed, each format's part
(seasynth.worker.export.parts) packed into a deterministic tar, then uploaded beside the KITTI tar before the commit marker.

Like the shard tar, a part becomes visible whole (one PUT or a completed multipart upload) under a key derived from
(dataset, shard, format) alone, and is a pure function of the shard's frames: a retried or duplicated shard uploads
the same bytes again.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from seasynth.service.records.types import ExportPart
from seasynth.service.shards import Shard, export_part_key
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.outputs import EXPORT_FORMATS
from seasynth.service.storage import ObjectStore
from seasynth.worker.export.parts import write_part
from seasynth.worker.queue.packing import pack_tar


@dataclass(frozen=True)
class PackedPart:
    """A part packed on local disk, not uploaded yet."""

    format: str
    path: Path
    sha256: str
    bytes: int


def keep_frame(root: Path, files: dict[str, bytes]) -> None:
    """Write one frame's files (relative path -> bytes) under `root`, for the parts built after the tar."""
    for rel, data in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def pack_parts(spec: DatasetSpec, shard: Shard, frames: Path, work: Path, code_version: str) -> list[PackedPart]:
    """Each of the spec's export formats for the shard's frames (kept under `frames`), packed under `work`."""
    packed = []
    for fmt in spec.outputs.exports:
        out = work / "parts" / fmt
        out.mkdir(parents=True)
        members = write_part(spec, fmt, shard.frames, frames, out, code_version)
        path = work / f"{fmt}.tar"
        with open(path, "wb") as f:
            sha, size = pack_tar(((m, (out / m).read_bytes()) for m in members), f)
        packed.append(PackedPart(fmt, path, sha, size))
    return packed


def upload_parts(store: ObjectStore, dataset_id: str, index: int, packed: list[PackedPart]) -> tuple[ExportPart, ...]:
    """Upload packed parts of shard `index` under their deterministic keys; what its commit marker lists."""
    parts = []
    for p in packed:
        key = export_part_key(dataset_id, index, p.format)
        store.put_file(key, p.path, "application/x-tar")
        parts.append(ExportPart(format=p.format, key=key, sha256=p.sha256, bytes=p.bytes))
    return tuple(parts)


def part_keys(dataset_id: str, index: int) -> tuple[str, ...]:
    """Every key an execution of shard `index` may have written a part to, whatever the spec asked for."""
    return tuple(export_part_key(dataset_id, index, fmt) for fmt in EXPORT_FORMATS)
