"""What a dataset's status record holds as read: its states, the record itself, and each committed shard's marker
(seasynth.service.records.store keeps them in Redis)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

from seasynth.service.spec.outputs import EXPORT_FORMATS

QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED = "queued", "running", "succeeded", "failed", "cancelled"
TERMINAL = frozenset({SUCCEEDED, FAILED, CANCELLED})


@dataclass(frozen=True)
class DatasetRecord:
    """One dataset's status as stored; counters are exact at the time of reading."""

    id: str
    created_at: float  # seconds since the epoch
    spec_json: str  # the validated spec, as stored (JSON text): parsed on first use of `spec`
    seed: int
    code_version: str
    renderer: str | None
    state: str
    frames_total: int
    shard_size: int
    shards_total: int
    frames_done: int
    shards_done: int
    shards_failed: int
    attempts: int
    started_at: float | None
    finished_at: float | None
    touched_at: float  # the last shard started, committed or failed, or the last planning or sweep
    purged: bool
    # failed shard -> its last error, for the seasynth.service.records.store.ERRORS_SHOWN failed shards of lowest index only
    errors: dict[int, str] = field(default_factory=dict)
    # when the record was rebuilt from the bucket after Redis lost it (seasynth.service.records.recovery): attempts, errors and
    # timings from before are lost; None for a record that never was
    restored_at: float | None = None
    # why the dataset is not progressing, where a worker knows: its shards wait for a worker of the renderer they
    # were started with (seasynth.worker.queue.pinning), or gave up on one; None otherwise
    notice: str | None = None

    @cached_property
    def spec(self) -> dict[str, Any]:
        """The validated spec. Parsed only when asked for: status reads and lists never need it, and parsing it
        was a quarter of the API's CPU per listed record (bench/load.py)."""
        return json.loads(self.spec_json)


@dataclass(frozen=True)
class ExportPart:
    """One shard's part of a generate-time export format (spec outputs.coco, yolo, mcap): a tar beside its KITTI
    tar (seasynth.service.shards.export_part_key)."""

    format: str  # coco, yolo or mcap
    key: str
    sha256: str  # lowercase hex of the whole object
    bytes: int


@dataclass(frozen=True)
class ShardCommit:
    """What a committed shard's marker says (the manifest's shard entries)."""

    index: int
    key: str
    first_frame: int
    frame_count: int
    sha256: str  # lowercase hex of the whole object
    bytes: int
    code_version: str
    renderer: str
    exports: tuple[ExportPart, ...] = ()  # in seasynth.service.spec.outputs.EXPORT_FORMATS order

    def to_json(self) -> str:
        """The marker's JSON; `exports` only when there are parts, so markers of shards without stay as they were."""
        data = {k: v for k, v in self.__dict__.items() if k != "exports"}
        if self.exports:
            data["exports"] = {p.format: {"key": p.key, "sha256": p.sha256, "bytes": p.bytes} for p in self.exports}
        return json.dumps(data, sort_keys=True)

    @classmethod
    def from_json(cls, text: str | bytes) -> ShardCommit:
        data = json.loads(text)
        parts = data.pop("exports", {})
        rank = {f: k for k, f in enumerate(EXPORT_FORMATS)}
        order = sorted(parts, key=lambda f: (rank.get(f, len(rank)), f))
        return cls(**data, exports=tuple(ExportPart(format=f, **parts[f]) for f in order))
