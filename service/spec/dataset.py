"""The dataset spec: what a dataset is, validated at every edge (files, HTTP bodies, task payloads)."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

from pydantic import Field, StrictInt, ValidationError, model_serializer, model_validator

from seasynth.service.errors import SpecError
from seasynth.service.spec.light import Lighting, Water
from seasynth.service.spec.outputs import Outputs
from seasynth.service.spec.scene import (
    AssetRef,
    Camera,
    Distractors,
    FileRef,
    Materials,
    Noise,
    Terrain,
    TextureRandomisation,
    Workspaces,
)
from seasynth.service.spec.sensors import Sensors, Trajectory
from seasynth.service.spec.targets import Labels, TargetClasses, Targets, legacy_form
from seasynth.service.spec.types import SpecModel

# Documented limits (the scene's are in seasynth.service.spec.scene). They keep one shard inside the task time limit, and
# every frame name within KITTI's six digits (000000 to 999999).
MAX_FRAMES = 1_000_000
MAX_SHARD_SIZE = 10_000
MAX_SHARD_MEGAPIXELS = 600.0  # shard_size * (width * height + sensors' render pixels) / 1e6

Quality = Literal["draft", "fast", "default", "high"]
TERRAIN_FILES = ("mesh", "texture", "normal_map", "height_map")  # the terrain's fields that name user files


class DatasetSpec(SpecModel):
    """A whole dataset. Every field has a default; unknown fields are refused."""

    seed: StrictInt = Field(0, ge=0, lt=2**63)
    frames: StrictInt = Field(100, ge=1, le=MAX_FRAMES)
    shard_size: StrictInt = Field(50, ge=1, le=MAX_SHARD_SIZE)
    quality: Quality = "default"
    camera: Camera = Camera()
    workspaces: Workspaces = Workspaces()
    # The classes of target, in the order that numbers them in every output (one mapping: a list of that class).
    targets: TargetClasses = Field(default_factory=lambda: [Targets()])
    distractors: Distractors = Distractors()
    terrain: Terrain = Terrain()
    lighting: Lighting = Lighting()
    water: Water = Water()
    texture: TextureRandomisation = TextureRandomisation()
    materials: Materials = Materials()
    noise: Noise = Noise()
    labels: Labels = Labels()
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

    @model_serializer(mode="wrap")
    def _targets_form(self, handler, info) -> dict[str, Any]:
        """Dumps write one seabed class as the mapping of specs before classes (seasynth.service.spec.targets
        .legacy_form), and leave it out with exclude_defaults when it is the default class."""
        out = handler(self)
        if "targets" in out:
            if info.exclude_defaults and self.targets == [Targets()]:
                del out["targets"]
            else:
                out["targets"] = legacy_form(out["targets"], self.targets)
        return out

    @property
    def class_names(self) -> tuple[str, ...]:
        """The target classes' names in spec order (class i: COCO category i + 1, YOLO class i, semantic id i + 1)."""
        return tuple(c.class_name for c in self.targets)

    def most_targets(self) -> int:
        """The most targets a frame may place: every class's count maximum (times its school size maximum)."""
        return sum(c.most_objects() for c in self.targets)

    def asset_refs(self) -> list[AssetRef]:
        return [*(a for c in self.targets for a in c.assets), *self.distractors.assets]

    def file_refs(self) -> list[tuple[str, FileRef]]:
        """Every user file the spec names, with the dotted field that names it."""
        out: list[tuple[str, FileRef]] = []
        groups = [(f"targets.{k}", c) for k, c in enumerate(self.targets)] if len(self.targets) > 1 else \
            [("targets", self.targets[0])]
        for role, group in (*groups, ("distractors", self.distractors)):
            for i, a in enumerate(group.assets):
                if a.procedural is None:
                    out.append((f"{role}.assets.{i}", a))
        for key in TERRAIN_FILES:
            ref = getattr(self.terrain, key)
            if ref is not None:
                out.append((f"terrain.{key}", ref))
        return out


def field_path(loc: tuple | list, data: Any) -> str:
    """A validation error's location in spec `data` as a dotted path, naming fields as written: where targets is
    one mapping, its fields are targets.count, not targets.0.count (the list of one it stands for)."""
    parts = list(loc)
    if parts[:2] == ["targets", 0] and isinstance(data, dict) and isinstance(data.get("targets"), dict):
        del parts[1]
    return ".".join(str(p) for p in parts)


def format_validation_error(err: ValidationError, data: Any = None) -> str:
    """One line per problem, each naming the field by its dotted path in `data`, the mapping validated."""
    lines = []
    for e in err.errors():
        loc = field_path(e["loc"], data) or "(spec)"
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
        raise SpecError(f"{source}: invalid spec\n{format_validation_error(err, data)}") from None


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
    return data if suffix == ".json" else _empty_sections(data, DatasetSpec)


def _empty_sections(data: dict[str, Any], model: type[SpecModel]) -> dict[str, Any]:
    """YAML reads a section with nothing under it (`camera:` with every line commented out) as null: such a section
    is empty, i.e. at its defaults, as an empty file is (and as apply_overrides reads it)."""
    out = dict(data)
    for key, value in data.items():
        field = model.model_fields.get(key) if isinstance(key, str) else None
        section = field.annotation if field is not None else None
        listed = get_origin(section) is list  # a list of sections (targets), which one mapping may stand for
        if listed:
            section = get_args(section)[0]
        if not (isinstance(section, type) and issubclass(section, SpecModel)):
            continue
        if value is None:
            out[key] = {}
        elif isinstance(value, dict):
            out[key] = _empty_sections(value, section)
        elif listed and isinstance(value, list):
            out[key] = [_empty_sections(v, section) if isinstance(v, dict) else v for v in value]
    return out


def resolve_paths(data: dict[str, Any], base: Path) -> dict[str, Any]:
    """Make relative asset/terrain paths in a spec mapping absolute against the spec file's folder."""

    def fix(p: Any) -> Any:
        return str((base / p).resolve()) if isinstance(p, str) and not Path(p).is_absolute() else p

    # Ill-typed parts are left as they are for validation to name; YAML may hold non-JSON values (dates).
    out = copy.deepcopy(data)
    refs = []
    targets = out.get("targets")
    for section in [*(targets if isinstance(targets, list) else [targets]), out.get("distractors")]:
        assets = section.get("assets") if isinstance(section, dict) else None
        refs += assets if isinstance(assets, list) else []
    terrain = out.get("terrain")
    if isinstance(terrain, dict):
        refs += [terrain.get(key) for key in TERRAIN_FILES]
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
