"""Admission of a POSTed spec: the configured limits (frames, resolution, objects, a shard's estimated time against
the task time limit) and the uploaded assets it names."""

from __future__ import annotations

from seasynth.api.asset_store import stored_format
from seasynth.api.deps import Services
from seasynth.api.uploads import ARTICLED, field_kind
from seasynth.service.errors import LimitExceeded, SpecError
from seasynth.service.settings import Settings
from seasynth.service.shards import asset_key, spec_cost_terms, spec_shard_seconds
from seasynth.service.spec.dataset import DatasetSpec


def check_limits(spec: DatasetSpec, settings: Settings) -> None:
    """LimitExceeded naming each configured limit the spec goes over."""
    over = []
    if spec.frames > settings.max_frames:
        over.append(f"frames: {spec.frames} is over the limit of {settings.max_frames} (SEASYNTH_MAX_FRAMES)")
    for side in ("width", "height"):
        v = getattr(spec.camera, side)
        if v > settings.max_side:
            over.append(f"camera.{side}: {v} is over the limit of {settings.max_side} (SEASYNTH_MAX_SIDE)")
    # One class: its count, as before classes; several: their count maxima together (a role's objects a frame).
    where = "targets.count: max" if len(spec.targets) == 1 else "targets: the classes' count maxima total"
    for what, hi in ((where, spec.most_targets()), ("distractors.count: max", spec.distractors.count[1])):
        if hi > settings.max_objects:
            over.append(f"{what} {hi} is over the limit of {settings.max_objects} objects (SEASYNTH_MAX_OBJECTS)")
    # A shard must finish well inside the task time limit on a slow worker (service/shards.py's cost model).
    shard = shard_over_time_limit(spec, settings.task_soft_time_limit_s)
    if shard is not None:
        over.append(shard)
    if over:
        raise LimitExceeded("\n".join(over))


def shard_over_time_limit(spec: DatasetSpec, budget: float) -> str | None:
    """Why a shard of `spec` would not finish well inside the task time limit on a slow worker, or None.

    Both the estimate and the suggested shard_size come from the full cost model (seasynth.service.shards.spec_shard_seconds:
    resolution and quality, objects, terrain cells and builds, extra outputs), so the suggestion really fits.
    """
    need = spec_shard_seconds(spec)
    if need <= budget:
        return None
    size = min(spec.shard_size, spec.frames)
    terms = spec_cost_terms(spec)
    sensors = (f", {terms['sensors']} sensors rendering {terms['sensor_pixels']} pixels"
               if terms["sensors"] else "")
    what = (f"shard_size: {size} frames of {spec.camera.width}x{spec.camera.height} at quality {spec.quality!r} "
            f"(up to {terms['objects']} objects, {terms['terrain_cells']} terrain cells a side, "
            f"{terms['terrain_builds']} terrains, {terms['extra_outputs']} of clean/range/depth/instance/coco/yolo/"
            f"mcap{sensors}) are estimated at {need:.0f} s per shard, over the limit of {budget} s (the soft task "
            f"time limit, SEASYNTH_TASK_TIME_LIMIT_S)")
    fits = largest_shard_size(spec, budget, below=size)
    if fits == 0:
        return (f"{what}; even one frame per shard is estimated at {spec_shard_seconds(spec, 1):.0f} s: lower the "
                "resolution, quality, object counts, terrain.cells or outputs"
                + (", or the sensors' beams and bins" if terms["sensors"] else ""))
    return f"{what}; use shard_size <= {fits}"


def largest_shard_size(spec: DatasetSpec, budget: float, below: int) -> int:
    """The largest shard size under `below` whose estimate fits `budget` (0: none does). Binary search: the
    estimate grows with the shard size."""
    lo, hi = 0, below - 1  # the answer is in [lo, hi]; a shard of 0 frames costs nothing
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if spec_shard_seconds(spec, mid) <= budget:
            lo = mid
        else:
            hi = mid - 1
    return lo


def check_files(spec: DatasetSpec, services: Services) -> None:
    """A POSTed spec names uploaded assets only, each of the kind its field needs (a mesh, or an image for
    terrain.texture, normal_map, height_map): SpecError naming every path, every unknown asset id and every asset
    of the wrong kind."""
    bad = []
    for where, ref in spec.file_refs():
        if ref.path is not None:
            bad.append(f"{where}.path: local paths and URLs are not accepted here; upload the file to POST /assets "
                       "and reference it by asset_id")
            continue
        fmt = stored_format(services, ref.asset_id)
        if fmt is None or services.store.head(asset_key(ref.asset_id)) is None:
            bad.append(f"{where}.asset_id: no uploaded asset {ref.asset_id}")
        elif fmt.kind != (need := field_kind(where)):
            bad.append(f"{where}.asset_id: asset {ref.asset_id} is {fmt}; this field needs {ARTICLED[need]}")
    if bad:
        raise SpecError("\n".join(bad))
