"""The dataset manifest: committed shards with sha256 and size (as Croissant's FileObject), spec, seed, versions."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from seasynth.service.records.types import DatasetRecord, ShardCommit

MANIFEST_FORMAT = "seasynth-manifest/1"


def build_manifest(
    record: DatasetRecord, commits: list[ShardCommit], url: Callable[[str], str] | None = None
) -> dict[str, Any]:
    """The manifest as a JSON object; `url` adds a download URL per shard and export part (presigned ones expire,
    so the stored manifest.json has none). A shard entry lists its export parts (spec outputs.coco, yolo, mcap) under
    `exports`: format -> {key, sha256, bytes}; shards of a spec without export formats have no `exports`."""
    shards = []
    for c in sorted(commits, key=lambda c: c.index):
        entry: dict[str, Any] = {
            "index": c.index,
            "key": c.key,
            "first_frame": c.first_frame,
            "frame_count": c.frame_count,
            "sha256": c.sha256,
            "bytes": c.bytes,
            "renderer": c.renderer,
        }
        if url is not None:
            entry["url"] = url(c.key)
        if c.exports:  # the shard's parts of the spec's export formats, each verified like the tar
            entry["exports"] = {
                p.format: {"key": p.key, "sha256": p.sha256, "bytes": p.bytes, **({"url": url(p.key)} if url else {})}
                for p in c.exports
            }
        shards.append(entry)
    return {
        "format": MANIFEST_FORMAT,
        "id": record.id,
        "state": record.state,
        "complete": len(shards) == record.shards_total,
        "frames_total": record.frames_total,
        "frames_done": sum(s["frame_count"] for s in shards),
        "shards_total": record.shards_total,
        "seed": record.seed,
        "code_version": record.code_version,
        "renderer": record.renderer,
        "spec": record.spec,
        "shards": shards,
    }


def manifest_bytes(manifest: dict[str, Any]) -> bytes:
    return (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode()
