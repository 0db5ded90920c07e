"""The dataset spec: what a dataset is, validated at every edge (files, HTTP bodies, task payloads)."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from service.errors import SpecError
from service.sensors import Sensors, Trajectory
from service.spec_light import Lighting, Water
from service.spec_types import (
    MAX_CHOICES,
    Interval,
    NonNegInterval,
    PositiveInterval,
    SpecModel,
    Vec3,
)

# Documented limits. They keep one frame inside memory and one shard inside the task time limit, and every frame
# name within KITTI's six digits (000000 to 999999).
MAX_FRAMES = 1_000_000
MAX_SIDE = 4096
MIN_SIDE = 8
MAX_SHARD_SIZE = 10_000
MAX_SHARD_MEGAPIXELS = 600.0  # shard_size * (width * height + sensors' render pixels) / 1e6
MAX_OBJECTS = 64  # per role and frame
MAX_TERRAIN_CELLS = 1024
MAX_VARIANTS = 1024
MAX_ASSETS = 256  # entries in targets.assets and in distractors.assets
MAX_PATH_CHARS = 4096

Quality = Literal["draft", "fast", "default", "high"]
ProceduralTarget = Literal["urchin", "rock", "coral", "seaweed", "clam"]
TerrainStyle = Literal["sand", "pebbles", "rock"]


def _count_range(v: tuple[int, int]) -> tuple[int, int]:
    if v[0] < 0:
        raise ValueError(f"counts must be >= 0, got min {v[0]}")
    if v[0] > v[1]:
        raise ValueError(f"min {v[0]} > max {v[1]}")
    if v[1] > MAX_OBJECTS:
        raise ValueError(f"max {v[1]} is over the limit of {MAX_OBJECTS} objects")
    return v


CountInterval = Annotated[tuple[StrictInt, StrictInt], AfterValidator(_count_range)]


class Box(SpecModel):
    """An axis-aligned box in world coordinates (metres, z up)."""

    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _check(self) -> Box:
        for axis, lo, hi in zip("xyz", self.min, self.max):
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"{axis} bounds must be finite")
            if lo > hi:
                raise ValueError(f"min {axis} {lo} > max {axis} {hi}")
        return self


class Intrinsics(SpecModel):
    fx: StrictFloat = Field(gt=0)
    fy: StrictFloat = Field(gt=0)
    cx: StrictFloat
    cy: StrictFloat


class Camera(SpecModel):
    width: StrictInt = Field(640, ge=MIN_SIDE, le=MAX_SIDE)
    height: StrictInt = Field(480, ge=MIN_SIDE, le=MAX_SIDE)
    # Horizontal field of view; the vertical one follows from the aspect ratio (square pixels).
    hfov_deg: StrictFloat | None = Field(None, gt=1.0, lt=170.0)
    intrinsics: Intrinsics | None = None
    clip: PositiveInterval = (0.02, 300.0)
    look_at_jitter_m: StrictFloat = Field(0.05, ge=0)

    @field_validator("clip")
    @classmethod
    def _near_before_far(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] >= v[1]:
            raise ValueError(f"near {v[0]} must be < far {v[1]}")
        return v

    @model_validator(mode="after")
    def _one_projection(self) -> Camera:
        if self.hfov_deg is not None and self.intrinsics is not None:
            raise ValueError("give either hfov_deg or intrinsics, not both")
        return self

    def K(self) -> list[list[float]]:
        """The 3x3 intrinsic matrix (pixels; pixel centres at integer coordinates)."""
        if self.intrinsics is not None:
            i = self.intrinsics
            return [[i.fx, 0.0, i.cx], [0.0, i.fy, i.cy], [0.0, 0.0, 1.0]]
        hfov = math.radians(70.0 if self.hfov_deg is None else self.hfov_deg)
        f = (self.width / 2.0) / math.tan(hfov / 2.0)
        return [[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]]


class FileRef(SpecModel):
    """A user file: a local path (spec files, CLI) or the sha256 id of an asset uploaded to the service."""

    path: str | None = Field(None, min_length=1, max_length=MAX_PATH_CHARS)
    asset_id: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")

    def _sources(self) -> list[str]:
        return [n for n in ("path", "asset_id") if getattr(self, n) is not None]

    @model_validator(mode="after")
    def _exactly_one(self) -> FileRef:
        if len(self._sources()) != 1:
            raise ValueError(f"give exactly one of path, asset_id (got {self._sources() or 'none'})")
        return self


class AssetRef(FileRef):
    """One object asset: exactly one of a procedural kind, a local file, or an uploaded asset id."""

    procedural: ProceduralTarget | None = None
    # Procedural kinds are built in this many deterministic variants, cached per process.
    variants: StrictInt = Field(8, ge=1, le=MAX_VARIANTS)

    def _sources(self) -> list[str]:
        return [n for n in ("procedural", "path", "asset_id") if getattr(self, n) is not None]

    @model_validator(mode="after")
    def _exactly_one(self) -> AssetRef:
        if len(self._sources()) != 1:
            raise ValueError(f"give exactly one of procedural, path, asset_id (got {self._sources() or 'none'})")
        return self


class Targets(SpecModel):
    class_name: str = Field("Urchin", pattern=r"^\S+$", max_length=64)
    assets: list[AssetRef] = Field(
        default_factory=lambda: [AssetRef(procedural="urchin")], min_length=1, max_length=MAX_ASSETS
    )
    count: CountInterval = (3, 8)
    scale: PositiveInterval = (0.8, 1.25)


class Distractors(SpecModel):
    assets: list[AssetRef] = Field(
        default_factory=lambda: [AssetRef(procedural=k) for k in ("rock", "coral", "seaweed", "clam")],
        min_length=1,
        max_length=MAX_ASSETS,
    )
    count: CountInterval = (4, 12)
    scale: PositiveInterval = (0.7, 1.4)


class Terrain(SpecModel):
    styles: list[TerrainStyle] = Field(
        default_factory=lambda: ["sand", "pebbles", "rock"], min_length=1, max_length=MAX_CHOICES
    )
    variants: StrictInt = Field(8, ge=1, le=MAX_VARIANTS)
    size_m: StrictFloat = Field(12.0, gt=0, le=1000)
    cells: StrictInt = Field(192, ge=2, le=MAX_TERRAIN_CELLS)
    relief_m: StrictFloat = Field(0.25, ge=0, le=100)
    # User terrain: a mesh file (replaces the procedural heightfield) and/or a colour texture.
    mesh: FileRef | None = None
    texture: FileRef | None = None
    texture_tile_m: StrictFloat = Field(1.0, gt=0)


class Workspaces(SpecModel):
    """The paper's four workspaces (world metres, z up)."""

    targets: Box = Box(min=(-2.0, -2.0, -5.0), max=(2.0, 2.0, 5.0))
    distractors: Box = Box(min=(-3.0, -3.0, -5.0), max=(3.0, 3.0, 5.0))
    camera: Box = Box(min=(-1.5, -3.0, 0.8), max=(1.5, -1.0, 2.0))
    look_at: Box = Box(min=(-2.0, -2.0, -5.0), max=(2.0, 2.0, 5.0))


class TextureRandomisation(SpecModel):
    """Per-channel albedo scale and bias, drawn per object (colour changes, pattern stays)."""

    scale: NonNegInterval = (0.75, 1.25)
    bias: Interval = (-0.04, 0.04)


class Noise(SpecModel):
    """Camera noise: off by default; recorded in meta when on."""

    gaussian_sigma: StrictFloat = Field(0.0, ge=0, le=0.5)


EXPORT_FORMATS = ("coco", "yolo", "mcap")  # detector formats written beside the KITTI files (worker.export)
SPLITS = ("train", "val", "test")
SPLIT_SUM_TOLERANCE = 1e-9


def split_problem(fractions: tuple[float, ...]) -> str | None:
    """Why `fractions` are no train, val, test split (three finite numbers >= 0 summing to 1 within 1e-9), or
    None. The one rule for outputs.split and `seasynth export --split`."""
    if len(fractions) != len(SPLITS):
        return f"give 3 fractions for train,val,test, got {len(fractions)}"
    if not all(math.isfinite(v) and v >= 0 for v in fractions):
        return "fractions must be finite and >= 0"
    if abs(math.fsum(fractions) - 1.0) > SPLIT_SUM_TOLERANCE:
        return f"fractions must sum to 1, they sum to {math.fsum(fractions):g}"
    return None


class Outputs(SpecModel):
    """The files every frame gets, and the training formats written beside them.

    coco, yolo, mcap: each shard of a service dataset also gets that format's files for its frames (one object per
    shard, listed in the manifest; `seasynth fetch --format` merges them); a local `seasynth generate` writes the
    whole dataset's export into OUT/export/{format}/. split: train, val, test fractions of those exports (frame i's
    split is drawn from (seed, i) alone: worker.export.split_of).
    """

    labels: StrictBool = True
    meta: StrictBool = True
    depth: StrictBool = False
    instance: StrictBool = False
    clean: StrictBool = False
    range: StrictBool = False
    coco: StrictBool = False
    yolo: StrictBool = False
    mcap: StrictBool = False
    split: tuple[StrictFloat, StrictFloat, StrictFloat] = (0.8, 0.1, 0.1)

    @field_validator("coco", "yolo", "mcap")
    @classmethod
    def _export_needs_labels(cls, on: bool, info) -> bool:
        if on and info.data.get("labels") is False:
            raise ValueError(f"needs outputs.labels: true (the {info.field_name} export's boxes are the label_2 "
                             "lines)")
        return on

    @field_validator("split")
    @classmethod
    def _split(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        problem = split_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v

    @property
    def exports(self) -> tuple[str, ...]:
        """The export formats switched on, in EXPORT_FORMATS order."""
        return tuple(f for f in EXPORT_FORMATS if getattr(self, f))


class DatasetSpec(SpecModel):
    """A whole dataset. Every field has a default; unknown fields are refused."""

    seed: StrictInt = Field(0, ge=0, lt=2**63)
    frames: StrictInt = Field(100, ge=1, le=MAX_FRAMES)
    shard_size: StrictInt = Field(50, ge=1, le=MAX_SHARD_SIZE)
    quality: Quality = "default"
    camera: Camera = Camera()
    workspaces: Workspaces = Workspaces()
    targets: Targets = Targets()
    distractors: Distractors = Distractors()
    terrain: Terrain = Terrain()
    lighting: Lighting = Lighting()
    water: Water = Water()
    texture: TextureRandomisation = TextureRandomisation()
    noise: Noise = Noise()
    outputs: Outputs = Outputs()
    sensors: Sensors = Sensors()
    trajectory: Trajectory = Trajectory()

    @model_validator(mode="after")
    def _resolve_water_model(self) -> DatasetSpec:
        """Name the water model in the spec itself when the spec leaves it unset (see Water): physical, unless the
        water gives paper-only fields or, with no depth_m given, the camera or a survey's vehicle reaches the
        default seabed depth (a spec written for the paper's model, which has no surface)."""
        w = self.water
        if w.model is not None:
            return self
        model = w.resolved_model
        if model == "physical" and "depth_m" not in w.model_fields_set:
            tr = self.trajectory
            top = self.workspaces.camera.max[2] if tr.kind == "random" else tr.altitude_m + tr.heave_m
            if top >= w.depth_m[0]:
                model = "paper"
        object.__setattr__(self, "water", w.model_copy(update={"model": model}))
        return self

    @model_validator(mode="after")
    def _camera_under_water(self) -> DatasetSpec:
        w = self.water
        if w.enabled and w.resolved_model == "physical" and w.depth_m[0] <= self.workspaces.camera.max[2]:
            raise ValueError(
                f"water.depth_m: min {w.depth_m[0]} m puts the surface at or below the top of workspaces.camera "
                f"(z = {self.workspaces.camera.max[2]} m): the camera must stay under water"
            )
        return self

    @model_validator(mode="after")
    def _trajectory_under_water(self) -> DatasetSpec:
        w, tr = self.water, self.trajectory
        top = tr.altitude_m + tr.heave_m
        if tr.kind != "random" and w.enabled and w.resolved_model == "physical" and w.depth_m[0] <= top:
            raise ValueError(f"trajectory.altitude_m: {tr.altitude_m} m + heave_m {tr.heave_m} m reaches the surface "
                             f"(water.depth_m min {w.depth_m[0]} m): the vehicle must stay under water")
        return self

    @model_validator(mode="after")
    def _lamps_and_caustics_need_physical_light(self) -> DatasetSpec:
        w = self.water
        if w.enabled and w.resolved_model == "physical":
            return self
        for field, on in (("caustics.enabled", self.lighting.caustics.enabled), ("lamps", self.lighting.lamps)):
            if on:
                raise ValueError(f"lighting.{field}: {field.split('.')[0]} are part of the physical light model; "
                                 "set water.model: physical (with water.enabled: true)")
        return self

    @model_validator(mode="after")
    def _shard_work(self) -> DatasetSpec:
        sensor_px = self.sensors.render_pixels()  # the sonars' and DVL's renders count as the camera's pixels do
        mp = self.shard_size * (self.camera.width * self.camera.height + sensor_px) / 1e6
        if mp > MAX_SHARD_MEGAPIXELS:
            sensors = f" plus {sensor_px} sensor render pixels (sensors.fls, sss, dvl)" if sensor_px else ""
            raise ValueError(
                f"shard_size: {self.shard_size} frames of {self.camera.width}x{self.camera.height}{sensors} is "
                f"{mp:.0f} megapixels per shard, over the limit of {MAX_SHARD_MEGAPIXELS:.0f}; lower shard_size"
            )
        return self

    def asset_refs(self) -> list[AssetRef]:
        return [*self.targets.assets, *self.distractors.assets]

    def file_refs(self) -> list[tuple[str, FileRef]]:
        """Every user file the spec names, with the dotted field that names it."""
        out: list[tuple[str, FileRef]] = []
        for role in ("targets", "distractors"):
            for i, a in enumerate(getattr(self, role).assets):
                if a.procedural is None:
                    out.append((f"{role}.assets.{i}", a))
        for key in ("mesh", "texture"):
            ref = getattr(self.terrain, key)
            if ref is not None:
                out.append((f"terrain.{key}", ref))
        return out


def format_validation_error(err: ValidationError) -> str:
    """One line per problem, each naming the field by its dotted path."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(spec)"
        msg = e["msg"].removeprefix("Value error, ")
        lines.append(f"{loc}: {msg}")
    return "\n".join(lines)


def parse_spec(data: Any, *, source: str = "spec") -> DatasetSpec:
    """Validate a mapping into a spec; raise SpecError naming each bad field."""
    if not isinstance(data, dict):
        raise SpecError(f"{source}: the spec must be a mapping, got {type(data).__name__}")
    try:
        return DatasetSpec.model_validate(data)
    except ValidationError as err:
        raise SpecError(f"{source}: invalid spec\n{format_validation_error(err)}") from None


def read_spec_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML (.yaml/.yml) or JSON (.json) spec file into a mapping."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".yaml", ".yml", ".json"):
        raise SpecError(f"{path}: spec files must end in .yaml, .yml or .json")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise SpecError(f"{path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise SpecError(f"{path}: cannot read spec file ({err.strerror or err})") from None
    import yaml

    try:
        data = json.loads(text) if suffix == ".json" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError) as err:  # json's errors are ValueErrors
        raise SpecError(f"{path}: not valid {suffix[1:].upper()}: {err}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise SpecError(f"{path}: the spec must be a mapping, got {type(data).__name__}")
    return data


def resolve_paths(data: dict[str, Any], base: Path) -> dict[str, Any]:
    """Make relative asset/terrain paths in a spec mapping absolute against the spec file's folder."""

    def fix(p: Any) -> Any:
        return str((base / p).resolve()) if isinstance(p, str) and not Path(p).is_absolute() else p

    # Ill-typed parts are left as they are for validation to name; YAML may hold non-JSON values (dates).
    out = copy.deepcopy(data)
    refs = []
    for role in ("targets", "distractors"):
        section = out.get(role)
        assets = section.get("assets") if isinstance(section, dict) else None
        refs += assets if isinstance(assets, list) else []
    terrain = out.get("terrain")
    if isinstance(terrain, dict):
        refs += [terrain.get("mesh"), terrain.get("texture")]
    for ref in refs:
        if isinstance(ref, dict) and "path" in ref:
            ref["path"] = fix(ref["path"])
    return out


def load_spec(path: str | Path, overrides: dict[str, Any] | None = None) -> DatasetSpec:
    """Load a spec file, apply dotted-key overrides (e.g. {"camera.width": 64}), validate."""
    path = Path(path)
    data = resolve_paths(read_spec_file(path), path.parent)
    try:
        data = apply_overrides(data, overrides or {})
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None
    return parse_spec(data, source=str(path))


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Return a copy of `data` with dotted keys set (None values are skipped)."""
    out = copy.deepcopy(data)
    for dotted, value in overrides.items():
        if value is None:
            continue
        node = out
        *parents, leaf = dotted.split(".")
        for i, p in enumerate(parents):
            if node.get(p) is None:  # `camera:` with nothing under it reads as null
                node[p] = {}
            if not isinstance(node[p], dict):
                raise SpecError(f"{'.'.join(parents[: i + 1])}: must be a mapping to set {dotted}")
            node = node[p]
        node[leaf] = value
    return out


def spec_digest(spec: DatasetSpec) -> str:
    """sha256 of the spec's canonical JSON: two equal specs have the same digest."""
    import hashlib

    # Fields at their defaults are left out: a field added later with a default that keeps earlier behaviour does
    # not change the digest of any spec written before it.
    canon = json.dumps(spec.model_dump(mode="json", exclude_defaults=True), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canon.encode()).hexdigest()
