"""What shard and frame tasks work with: the per-process ShardContext, a shard's outcomes, the exceptions that send
a shard back (RetryShard, WrongVersion, WrongRenderer)."""

from __future__ import annotations

import socket
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Protocol

from seasynth.service import __version__
from seasynth.service.records.store import Records
from seasynth.service.settings import Settings
from seasynth.service.spec.dataset import DatasetSpec, parse_spec
from seasynth.service.storage import ObjectStore


class FrameSource(Protocol):
    """What a shard needs of the pipeline's RenderSession."""

    renderer_name: str

    def frame_files(self, spec: DatasetSpec, index: int) -> dict[str, bytes]: ...


class Outcome(str, Enum):
    COMMITTED = "committed"
    ALREADY_COMMITTED = "already-committed"
    RUNNING_ELSEWHERE = "running-elsewhere"  # a reconciler's copy found the shard running within its lease
    CANCELLED = "cancelled"
    MISSING = "missing"  # no such dataset (expired or never created)
    FAILED = "failed"
    DEFERRED = "deferred"  # pinned to another renderer: handed back for a worker that has it


class RetryShard(Exception):
    """The attempt failed with attempts left: run the shard again after `countdown` seconds."""

    def __init__(self, message: str, countdown: float):
        super().__init__(message)
        self.countdown = countdown


class WrongVersion(Exception):
    """A shard of a dataset pinned to another code version reached this worker; it must go back untouched."""

    def __init__(self, version: str):
        super().__init__(f"dataset is pinned to code version {version}, this worker runs {__version__}")
        self.version = version


class WrongRenderer(Exception):
    """A shard or frame of a dataset pinned to another GL renderer reached this worker; it must go back untouched."""

    def __init__(self, dataset_id: str, pinned: str, ours: str):
        super().__init__(f"dataset {dataset_id} is rendered with {pinned!r}; this worker runs {ours!r}")
        self.pinned = pinned


@dataclass
class ShardContext:
    """Per-process resources a shard or frame task uses; built in each pool process after the fork."""

    settings: Settings
    records: Records
    raw_redis: Any  # a redis client with decode_responses=False, for frame answers
    store: ObjectStore
    session: FrameSource
    host: str = field(default_factory=socket.gethostname)
    code_version: str = __version__
    _specs: dict[str, DatasetSpec] = field(default_factory=dict)

    def spec(self, dataset_id: str, spec_json: dict[str, Any]) -> DatasetSpec:
        """The dataset's spec, parsed once per process (a few recent datasets are kept)."""
        if dataset_id not in self._specs:
            if len(self._specs) >= 16:
                self._specs.pop(next(iter(self._specs)))
            self._specs[dataset_id] = parse_spec(spec_json, source=f"dataset {dataset_id}")
        return self._specs[dataset_id]
