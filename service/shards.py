"""Shard planning and the deterministic object keys of a dataset's shards, export parts, commit markers, manifest
and previews."""

from __future__ import annotations

import re
from dataclasses import dataclass

from seasynth.service.spec.dataset import MAX_FRAMES

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


# Admission's render cost model: an upper bound, not a forecast, of one worker process's seconds on a slow CPU
# worker (2 cores, Mesa llvmpipe, as many render processes as cores). Calibrated with RenderSession.frame_files
# and `seasynth generate --workers 2` on a 2-core llvmpipe machine (bench numbers in the docstrings below); each
# term stays 2.5-10x above what was measured, so a shard admitted here finishes inside the task time limit there.
# GPU workers are several times faster still.
FRAME_OVERHEAD_S = 0.25  # scene sampling, labels, PNG encoding: per frame, whatever the resolution (measured 0.07)
SAMPLES_PER_S = 2e6  # rendered and water-formed samples per second, per worker process (measured 5e6-2e7)
# Samples per output pixel of each quality preset (worker/frame/function.py PRESETS: msaa * supersample**2).
SAMPLES_PER_PIXEL = {"draft": 1, "fast": 4, "default": 4, "high": 16}
OBJECT_S = 0.004  # per placed object and frame: draw, placement, a target's labels (measured 0.001)
TERRAIN_CELL_S = 1e-6  # per heightfield cell (cells**2 of them) and frame: drawing it (measured 3e-7)
TERRAIN_BUILD_CELL_S = 1e-5  # per cell, once per distinct terrain a process draws: build, upload (measured 4.5e-6)
OUTPUT_SHARE = 0.25  # each of clean, range, depth, instance: this share of the image's sample cost again
# Export formats (outputs.coco, yolo, mcap) count as outputs too: each writes the shard's images again with its
# labels, and COCO also renders and encodes the instance ids.
EXTRA_OUTPUTS = ("clean", "range", "depth", "instance", "semantic", "coco", "yolo", "mcap")
# Sonar and navigation sensors (seasynth.service.spec.sensors): their renders (one sample per pixel, then the echo model's numpy
# work per pixel) and a fixed cost per enabled sensor. Measured on the same machine: FLS at defaults (852,044 render
# pixels) 0.219 s, i.e. 3.9e6 pixels/s; SSS at defaults (2 x 27,060 pixels) 0.016 s; DVL + pressure 0.014 s.
SENSOR_PIXELS_PER_S = 1e6
SENSOR_S = 0.05  # per enabled sensor and frame (measured 0.007-0.016)
# A user terrain mesh is costed as the largest heightfield (service/spec/scene.py MAX_TERRAIN_CELLS): its triangle
# count is unknown before it is loaded.
MAX_TERRAIN_CELLS_COSTED = 1024


def frame_seconds(
    width: int,
    height: int,
    quality: str,
    *,
    objects: int = 0,
    terrain_cells: int = 0,
    extra_outputs: int = 0,
    sensors: int = 0,
    sensor_pixels: int = 0,
) -> float:
    """Conservative seconds of one frame on one worker process (terrain builds excluded: see shard_seconds).

    objects: the most objects a frame may place (the upper ends of targets.count and distractors.count);
    terrain_cells: cells per side of the terrain grid; extra_outputs: how many of clean, range, depth, instance
    and the export formats coco, yolo and mcap are switched on; sensors: how many sonar and navigation sensors are
    on; sensor_pixels: the pixels they render per frame (seasynth.service.spec.sensors.Sensors.render_pixels).
    """
    samples = width * height * SAMPLES_PER_PIXEL[quality] / SAMPLES_PER_S
    return (FRAME_OVERHEAD_S + samples * (1 + OUTPUT_SHARE * extra_outputs) + OBJECT_S * objects
            + TERRAIN_CELL_S * terrain_cells**2 + SENSOR_S * sensors + sensor_pixels / SENSOR_PIXELS_PER_S)


def shard_seconds(
    shard_size: int,
    width: int,
    height: int,
    quality: str,
    *,
    objects: int = 0,
    terrain_cells: int = 0,
    extra_outputs: int = 0,
    terrain_builds: int = 0,
    sensors: int = 0,
    sensor_pixels: int = 0,
) -> float:
    """Conservative seconds one worker process needs for a full shard of these frames.

    terrain_builds: how many distinct terrains the shard may draw, each built once by a fresh process (at most
    one per frame). With only the first four arguments, only resolution and quality are costed: admission uses
    spec_shard_seconds, which fills in the rest from the spec.
    """
    frame = frame_seconds(width, height, quality, objects=objects, terrain_cells=terrain_cells,
                          extra_outputs=extra_outputs, sensors=sensors, sensor_pixels=sensor_pixels)
    builds = min(terrain_builds, shard_size) * TERRAIN_BUILD_CELL_S * terrain_cells**2
    return shard_size * frame + builds


def spec_cost_terms(spec) -> dict[str, int]:
    """The keyword arguments of shard_seconds for a DatasetSpec (seasynth.service.spec.dataset), as admission counts them."""
    t = spec.terrain
    cells = MAX_TERRAIN_CELLS_COSTED if t.mesh is not None else t.cells
    return {
        "objects": spec.most_targets() + spec.distractors.count[1],
        "terrain_cells": cells,
        "extra_outputs": sum(bool(getattr(spec.outputs, name)) for name in EXTRA_OUTPUTS),
        # A user mesh is one terrain; procedural ones come in len(styles) x variants (repeats weight the draw).
        "terrain_builds": 1 if t.mesh is not None else len(set(t.styles)) * t.variants,
        "sensors": spec.sensors.enabled_count,
        "sensor_pixels": spec.sensors.render_pixels(),
    }


def spec_shard_seconds(spec, shard_size: int | None = None) -> float:
    """Conservative seconds one worker process needs for a full shard of `spec` (default: spec.shard_size, capped
    at spec.frames).

    Calibration (2 cores, llvmpipe, 2 render processes at once; seconds per frame, model in brackets): 640x480
    draft, 1+1 objects, 16 cells, labels: 0.07 (0.41); with 64 targets: 0.12 (0.66); with 1024 cells: 0.38
    (1.45), plus 4.6 for each terrain not drawn before (10.5); 64+64 objects, 1024 cells and every output: 0.65
    (2.12). `seasynth generate --workers 2`: that last spec (3 styles x 8 variants of terrain), 8 frames in 21.9 s,
    about 5 s per frame and process (a 4-frame shard: 50 s modelled); the default spec, 8 frames in 4.0 s (an
    8-frame shard: 10.8 s modelled); 1280x960 high with depth and range, 4 frames in 6.5 s (a 4-frame shard: 62 s
    modelled).
    """
    size = min(spec.shard_size, spec.frames) if shard_size is None else shard_size
    return shard_seconds(size, spec.camera.width, spec.camera.height, spec.quality, **spec_cost_terms(spec))


# Host memory of one render process, an upper bound fitted to peaks measured with llvmpipe (which keeps GL
# buffers in host memory) for one frame with every output: 2048x2048 high 1.7 GB; 4096x4096 draft 2.2 GB,
# default 3.0 GB, high 6.1 GB. Caches that outlive a frame (terrains: about 0.5 GB each at 1024 cells) come on top;
# worker_max_memory_per_child (worker/queue/app.py) bounds what a process carries into its next task.
PROCESS_BASE_BYTES = 384 * 2**20  # interpreter, numpy, trimesh, Mesa, the caches of a small spec
FRAME_BYTES_PER_PIXEL = 128  # read-back images, labels, outputs, PNG encoding
FRAME_BYTES_PER_SAMPLE = 16  # multisampled colour, range and ids before the resolve


def frame_memory_bytes(width: int, height: int, quality: str) -> int:
    """Upper bound of a render process's memory while it renders one frame (caches excluded)."""
    pixels = width * height
    samples = pixels * SAMPLES_PER_PIXEL[quality]
    return PROCESS_BASE_BYTES + FRAME_BYTES_PER_PIXEL * pixels + FRAME_BYTES_PER_SAMPLE * samples


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


def export_part_key(dataset_id: str, index: int, fmt: str) -> str:
    """A shard's part of export format `fmt` (coco, yolo, mcap): an uncompressed tar in shards/{fmt}/, beside the
    KITTI tars and out of their shard-*.tar names."""
    return f"datasets/{dataset_id}/shards/{fmt}/shard-{index:06d}.tar"


def preview_key(dataset_id: str, digest: str) -> str:
    """A cached contact sheet; `digest` is the sha256 of what it was drawn from (seasynth.service.previews)."""
    return f"datasets/{dataset_id}/previews/{digest}.png"


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


def asset_thumbnail_key(asset_id: str) -> str:
    """An uploaded mesh's picture (PNG); beside it `.json` holds why none could be drawn, where it could not."""
    return f"assets/thumbnails/{asset_id}.png"


# Single files of one frame, by the `part` a client asks for: (folder, suffix) of its relative path.
FRAME_PARTS: dict[str, tuple[str, str]] = {
    "image": ("image_2", ".png"),
    "label": ("label_2", ".txt"),
    "calib": ("calib", ".txt"),
    "meta": ("meta", ".json"),
    "depth": ("depth", ".png"),
    "instance": ("instance", ".png"),
    "semantic": ("semantic", ".png"),
    "clean": ("clean", ".png"),
    "range": ("range", ".npy"),
    # Sonar and navigation sensors (seasynth.service.spec.sensors), where the spec switches them on.
    "fls": ("fls", ".png"),
    "fls_fan": ("fls_fan", ".png"),
    "fls_label": ("fls_label", ".json"),
    "sss": ("sss", ".png"),
    "sss_label": ("sss_label", ".json"),
    "nav": ("nav", ".json"),
}
# Each sensor's parts (seasynth.service.spec.sensors): a frame has them where the spec switches that sensor on.
PARTS_OF_SENSOR: dict[str, tuple[str, ...]] = {"fls": ("fls", "fls_fan", "fls_label"), "sss": ("sss", "sss_label"),
                                               "nav": ("nav",)}
SENSOR_PARTS = tuple(part for parts in PARTS_OF_SENSOR.values() for part in parts)
# Media types of a frame's files by suffix (GET /datasets/{id}/frames/{i}, the playground's data URLs).
MEDIA_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".txt": "text/plain; charset=utf-8",
               ".json": "application/json", ".npy": "application/octet-stream"}


def media_type(path: str) -> str:
    """The media type of a frame file (a relative path from frame_file) by its suffix."""
    return MEDIA_TYPES.get("." + path.rsplit(".", 1)[-1].lower(), "application/octet-stream")


def frame_name(index: int) -> str:
    """KITTI's six-digit file stem of frame `index` (the spec's frame limit keeps every index below 10^6)."""
    if not 0 <= index < MAX_FRAMES:
        raise ValueError(f"frame index {index} is outside 0..{MAX_FRAMES - 1}")
    return f"{index:06d}"


def frame_file(part: str, index: int, image_suffix: str = ".png") -> str:
    """The relative path of one of a frame's files, as a local generate writes it: image_2/000123.png.
    image_suffix: the image's (the spec's outputs.image_suffix: .png or .jpg)."""
    return named_file(part, frame_name(index), image_suffix)


def named_file(part: str, name: str, image_suffix: str = ".png") -> str:
    """frame_file of the frame whose file stem is `name` ("000123"), for readers that walk a dataset's names."""
    folder, suffix = FRAME_PARTS[part]
    return f"{folder}/{name}{image_suffix if part == 'image' else suffix}"


def frame_parts(spec) -> list[str]:
    """The parts (FRAME_PARTS keys) every frame of `spec` (a seasynth.service.spec.dataset.DatasetSpec) has."""
    o, s = spec.outputs, spec.sensors
    wanted = (("image", True), ("calib", True), ("label", o.labels), ("meta", o.meta), ("depth", o.depth),
              ("instance", o.instance), ("semantic", o.semantic), ("clean", o.clean), ("range", o.range))
    sensors_on = {"fls": s.fls.enabled, "sss": s.sss.enabled, "nav": s.any_nav}
    return [part for part, want in wanted if want] + [
        part for sensor, parts in PARTS_OF_SENSOR.items() if sensors_on[sensor] for part in parts]
