"""What every export format shares: the train/val/test split rule (seeded per frame), what an exporter is told
before the first frame (ExportInfo) and the Exporter protocol the formats implement."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from seasynth.service.camera_model import CameraModel
from seasynth.service.errors import ExportError
from seasynth.service.seeds import frame_rng
from seasynth.service.spec.outputs import IMAGE_SUFFIXES, SPLITS, split_problem
from seasynth.service.spec.scene import Camera
from seasynth.service.spec.sensors import Sensors, Trajectory
from seasynth.worker.export.dataset import Frame

# The split's own stream of SeedSequence([dataset seed, frame index, stream]); far from the frame's streams
# (seasynth.service.seeds: 0 scene, 1 noise) so no stream added there later draws the same numbers. ASCII "splt".
STREAM_SPLIT = 0x73706C74


def parse_split(text: str) -> tuple[float, float, float]:
    """"0.8,0.1,0.1" -> (train, val, test) fractions: three finite numbers >= 0 summing to 1 (within 1e-9)."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != len(SPLITS):
        raise ExportError(f"split {text!r}: give 3 comma-separated fractions for train,val,test, got {len(parts)}")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise ExportError(f"split {text!r}: fractions must be numbers") from None
    problem = split_problem(values)
    if problem is not None:
        raise ExportError(f"split {text!r}: {problem}")
    return values  # type: ignore[return-value]


def split_bounds(fractions: tuple[float, float, float]) -> tuple[float, float, float]:
    """Upper bounds of u for train, val, test: the cumulative fractions, the last nonzero one set to exactly 1.

    So u in [0, 1) always lands in a split of nonzero fraction, whatever the rounding of the sums.
    """
    bounds = list(np.cumsum(fractions, dtype=np.float64))
    last = max(k for k, f in enumerate(fractions) if f > 0)
    for k in range(last, len(bounds)):
        bounds[k] = 1.0
    return tuple(float(b) for b in bounds)  # type: ignore[return-value]


def split_of(dataset_seed: int, frame_index: int, fractions: tuple[float, float, float]) -> int:
    """Index into SPLITS of frame `frame_index`: a pure function of (dataset seed, frame index, fractions).

    u = Generator(PCG64(SeedSequence([dataset_seed, frame_index, STREAM_SPLIT]))).random(), uniform in [0, 1);
    the frame goes to the first split whose cumulative fraction exceeds u (split_bounds). Nothing else (the
    shard layout, worker count, other frames, --partial) enters, so a frame's split never changes with them.
    """
    u = frame_rng(dataset_seed, frame_index, STREAM_SPLIT).random()
    return next(k for k, bound in enumerate(split_bounds(fractions)) if u < bound)


@dataclass(frozen=True)
class ExportInfo:
    """What every exporter is told before the first frame."""

    out: Path  # absolute
    categories: tuple[str, ...]  # category index -> name: the spec's target classes, then "distractor" if asked
    width: int  # px, every frame's
    height: int  # px
    dataset_seed: int
    spec_sha256: str
    code_version: str | None  # the dataset's
    fractions: tuple[float, float, float]  # train, val, test
    sensors: Sensors = Sensors()  # the spec's sonar and navigation sensors (their files are in Frame.sensor_files)
    image_format: str = "png"  # the frames' image_2 files (the spec's outputs.image_format: png or jpeg)
    trajectory: Trajectory = Trajectory()  # the spec's: when each frame was taken (MCAP's stamps)
    distractors: bool = False  # the last category is "distractor" (export --distractors)
    # The camera model (seasynth.service.camera_model.CameraModel.record: K, Brown-Conrady distortion, port) where
    # the spec has a port or a distortion; None: the calib's pinhole is the whole camera.
    camera: dict | None = None

    @property
    def image_suffix(self) -> str:
        return IMAGE_SUFFIXES[self.image_format]


class Exporter(Protocol):
    """One output format. `add` gets frames in ascending index, each with its split; `finish` writes what
    spans frames. Every file is written under a temporary name and renamed (seasynth.worker.export.files)."""

    needs_masks: bool  # whether `add` reads Frame.instance and the objects' pixel counts
    # Globs (under the export folder) of the files spanning frames that exports of this format write, an earlier or
    # a fetched one's included (MCAP's *.mcap: {split}.mcap, and fetch --format's {split}-{shard}.mcap)
    folder_globs: tuple[str, ...]

    def frame_outputs(self, split: str, name: str) -> tuple[str, ...]:
        """Relative paths (under the export folder) written for frame `name` ("000123") in `split`."""
        ...

    def folder_outputs(self) -> tuple[str, ...]:
        """Relative paths of the files spanning frames that this export writes (matches of folder_globs)."""
        ...

    def begin(self, info: ExportInfo) -> None: ...

    def add(self, frame: Frame, split: str) -> None: ...

    def finish(self) -> None:
        """Write the files that span frames (COCO's instances_*.json, YOLO's data.yaml)."""
        ...

    def abort(self) -> None:
        """Remove the temporary files of an export that stopped early (frame files already placed stay)."""
        ...


def camera_record(camera: Camera) -> dict | None:
    """ExportInfo.camera of a spec's camera section."""
    model = CameraModel.from_spec(camera)
    return None if model.pinhole else model.record()
