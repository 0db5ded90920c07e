"""Shard planning and the deterministic object keys of a dataset's shards, commit markers and manifest."""

from __future__ import annotations

import re
from dataclasses import dataclass

DATASET_ID = re.compile(r"^[0-9a-f]{32}$")
ASSET_ID = re.compile(r"^[0-9a-f]{64}$")


@dataclass(frozen=True)
class Shard:
    """Frames [first_frame, first_frame + frame_count) of a dataset."""

    index: int
    first_frame: int
    frame_count: int

    @property
    def frames(self) -> range:
        return range(self.first_frame, self.first_frame + self.frame_count)


# Admission's render cost model, deliberately pessimistic: a one-worker `generate` on 2-core llvmpipe measured
# 107 ms for a 640x480 `default` frame (1.2 M samples), which this model puts at 0.86 s. GPUs are faster still.
FRAME_OVERHEAD_S = 0.25  # scene sampling, labels, PNG encoding: per frame, whatever the resolution
SAMPLES_PER_S = 2e6  # rendered and water-formed samples per second, per worker process
# Samples per output pixel of each quality preset (worker/pipeline.py PRESETS: msaa * supersample**2).
SAMPLES_PER_PIXEL = {"draft": 1, "fast": 4, "default": 4, "high": 16}


def shard_seconds(shard_size: int, width: int, height: int, quality: str) -> float:
    """Conservative seconds one worker process needs for a full shard of these frames."""
    return shard_size * (FRAME_OVERHEAD_S + width * height * SAMPLES_PER_PIXEL[quality] / SAMPLES_PER_S)


def shard_count(frames: int, shard_size: int) -> int:
    if frames < 1 or shard_size < 1:
        raise ValueError(f"frames and shard_size must be >= 1, got {frames}, {shard_size}")
    return -(-frames // shard_size)


def shard_at(frames: int, shard_size: int, index: int) -> Shard:
    """Shard `index` of a dataset: consecutive frames, the last shard possibly shorter."""
    n = shard_count(frames, shard_size)
    if not 0 <= index < n:
        raise ValueError(f"shard index {index} outside [0, {n})")
    first = index * shard_size
    return Shard(index, first, min(shard_size, frames - first))


def dataset_prefix(dataset_id: str) -> str:
    return f"datasets/{dataset_id}/"


def shard_key(dataset_id: str, index: int, compression: str = "none") -> str:
    """The final key of a shard's tar; users fetch everything under datasets/{id}/shards/."""
    suffix = ".tar.gz" if compression == "gz" else ".tar"
    return f"datasets/{dataset_id}/shards/shard-{index:06d}{suffix}"


def commit_key(dataset_id: str, index: int) -> str:
    """A shard's commit marker, written after its tar is complete; kept out of shards/ so the folder holds data."""
    return f"datasets/{dataset_id}/commits/shard-{index:06d}.json"


def commit_prefix(dataset_id: str) -> str:
    return f"datasets/{dataset_id}/commits/"


def manifest_key(dataset_id: str) -> str:
    """The manifest sits beside the shards."""
    return f"datasets/{dataset_id}/shards/manifest.json"


def asset_key(asset_id: str) -> str:
    return f"assets/{asset_id}"


def asset_info_key(asset_id: str) -> str:
    """A small JSON sidecar with the uploaded file's name (its suffix tells loaders the format)."""
    return f"assets/{asset_id}.json"


# Single files of one frame, by the `part` a client asks for: (folder, suffix) of its relative path.
FRAME_PARTS: dict[str, tuple[str, str]] = {
    "image": ("image_2", ".png"),
    "label": ("label_2", ".txt"),
    "calib": ("calib", ".txt"),
    "meta": ("meta", ".json"),
    "depth": ("depth", ".png"),
    "instance": ("instance", ".png"),
    "clean": ("clean", ".png"),
    "range": ("range", ".npy"),
}


def frame_file(part: str, index: int) -> str:
    """The relative path of one of a frame's files, as a local generate writes it: image_2/000123.png."""
    folder, suffix = FRAME_PARTS[part]
    return f"{folder}/{index:06d}{suffix}"
