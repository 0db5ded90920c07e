"""The scene sections of the dataset spec: camera, objects and their assets, terrain, workspaces, randomisation."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from seasynth.service.spec.optics import Distortion, Port, check_distortion, distortion_folds
from seasynth.service.spec.lens import Lens, Noise  # noqa: F401 (Noise: the spec's sections are imported from here)
from seasynth.service.spec.types import (
    MAX_CHOICES,
    MAX_MAGNITUDE,
    Interval,
    NonNegInterval,
    PositiveInterval,
    SpecModel,
    Vec3,
    within,
)

# Documented limits (with seasynth.service.spec.dataset's): they keep one frame inside memory.
MAX_SIDE = 4096
MIN_SIDE = 8
MAX_OBJECTS = 64  # per role and frame
MAX_TERRAIN_CELLS = 1024
MAX_VARIANTS = 1024
MAX_ASSETS = 256  # entries in targets.assets and in distractors.assets
MAX_PATH_CHARS = 4096

ProceduralTarget = Literal["urchin", "rock", "coral", "seaweed", "clam",
                          "starfish", "sea_cucumber", "scallop", "anemone", "sponge", "fish",
                          "plastic_bottle", "glass_bottle", "can", "tyre", "rope", "net", "cinder_block", "pipe"]
TerrainStyle = Literal["sand", "pebbles", "rock"]


def _count_range(v: tuple[int, int]) -> tuple[int, int]:
    if v[0] < 0:
        raise ValueError(f"counts must be >= 0, got min {v[0]}")
    if v[0] > v[1]:
        raise ValueError(f"min {v[0]} > max {v[1]}")
    if v[1] > MAX_OBJECTS:
        raise ValueError(f"max {v[1]} is over the limit of {MAX_OBJECTS} objects")
    return v


Count = Annotated[StrictInt, WithJsonSchema({"type": "integer", "minimum": 0, "maximum": MAX_OBJECTS})]
CountInterval = Annotated[tuple[Count, Count], AfterValidator(_count_range)]


def exactly_one_of(*names: str) -> dict:
    """JSON schema stating that exactly one of these fields is given and not null (what _exactly_one checks)."""
    return {"oneOf": [{"required": [n], "properties": {n: {"not": {"type": "null"}}}} for n in names]}


# An object's scale against its asset's size: up to 100x (an urchin asset 10 m wide).
ScaleInterval = Annotated[PositiveInterval, AfterValidator(lambda v: within(v, 0, 100))]


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
    fx: StrictFloat = Field(gt=0, le=MAX_MAGNITUDE)
    fy: StrictFloat = Field(gt=0, le=MAX_MAGNITUDE)
    cx: StrictFloat = Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)
    cy: StrictFloat = Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)


class Camera(Lens):
    # The schema states half of _one_projection: not both hfov_deg and intrinsics.
    model_config = ConfigDict(json_schema_extra={"not": {
        "required": ["hfov_deg", "intrinsics"],
        "properties": {"hfov_deg": {"not": {"type": "null"}}, "intrinsics": {"not": {"type": "null"}}}}})

    width: StrictInt = Field(640, ge=MIN_SIDE, le=MAX_SIDE)
    height: StrictInt = Field(480, ge=MIN_SIDE, le=MAX_SIDE)
    # Horizontal field of view; the vertical one follows from the aspect ratio (square pixels).
    hfov_deg: StrictFloat | None = Field(None, gt=1.0, lt=170.0)
    intrinsics: Intrinsics | None = None
    clip: PositiveInterval = (0.02, 300.0)
    look_at_jitter_m: StrictFloat = Field(0.05, ge=0, le=100)
    # The housing's window (kind none: a pinhole in water, as before); seasynth.service.camera_model maps pixels to
    # rays in water (docs/optics.md).
    port: Port = Port()
    # The lens's Brown-Conrady distortion [k1, k2, p1, p2, k3] in OpenCV's order, on normalised image coordinates
    # (all zero: none).
    distortion: Annotated[Distortion, AfterValidator(check_distortion)] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @field_validator("clip")
    @classmethod
    def _near_before_far(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] >= v[1]:
            raise ValueError(f"near {v[0]} must be < far {v[1]}")
        return v

    @field_validator("distortion")
    @classmethod
    def _invertible(cls, v: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        """The distortion's radial map keeps growing out to the image's corners (one ray a pixel)."""
        d = info.data
        if not {"width", "height", "hfov_deg", "intrinsics"} <= d.keys():
            return v  # another field is refused
        K = camera_K(d["width"], d["height"], d["hfov_deg"], d["intrinsics"])
        folds = distortion_folds(v, K, d["width"], d["height"])
        if folds is not None:
            raise ValueError(f"{list(v)} folds the image over: its radial map stops growing at r = {folds:.4g} "
                             f"(normalised), inside the image's corners")
        return v

    @model_validator(mode="after")
    def _one_projection(self) -> Camera:
        if self.hfov_deg is not None and self.intrinsics is not None:
            raise ValueError("give either hfov_deg or intrinsics, not both")
        i = self.intrinsics
        if i is not None:  # the same bound as hfov_deg's, on each axis: a focal length that sees less than 170 deg
            for name, f, side in (("fx", i.fx, self.width), ("fy", i.fy, self.height)):
                if 2 * math.degrees(math.atan(side / (2 * f))) >= 170.0:
                    raise ValueError(f"intrinsics.{name} {f} px gives a field of view of 170 deg or more over "
                                     f"{side} px; at least {side / (2 * math.tan(math.radians(85.0))):.4g}")
        return self

    @model_validator(mode="after")
    def _focus_beyond_focal_length(self) -> Camera:
        """With `aperture_f`, `focus_m` lies beyond the focal length, fx * sensor_width_mm / 1000 / width metres."""
        self.check_focus(self.K()[0][0], self.width)
        return self

    def K(self) -> list[list[float]]:
        """The 3x3 intrinsic matrix (pixels; pixel centres at integer coordinates)."""
        return camera_K(self.width, self.height, self.hfov_deg, self.intrinsics)


def camera_K(width: int, height: int, hfov_deg: float | None, intrinsics: Intrinsics | None) -> list[list[float]]:
    """The 3x3 intrinsic matrix of a camera section's fields (pixels; pixel centres at integer coordinates)."""
    if intrinsics is not None:
        i = intrinsics
        return [[i.fx, 0.0, i.cx], [0.0, i.fy, i.cy], [0.0, 0.0, 1.0]]
    hfov = math.radians(70.0 if hfov_deg is None else hfov_deg)
    f = (width / 2.0) / math.tan(hfov / 2.0)
    return [[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]]


class FileRef(SpecModel):
    """A user file: a local path (spec files, CLI) or the sha256 id of an asset uploaded to the service."""

    model_config = ConfigDict(json_schema_extra=exactly_one_of("path", "asset_id"))

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

    model_config = ConfigDict(json_schema_extra=exactly_one_of("procedural", "path", "asset_id"))

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


class Distractors(SpecModel):
    assets: list[AssetRef] = Field(
        default_factory=lambda: [AssetRef(procedural=k) for k in ("rock", "coral", "seaweed", "clam")],
        min_length=1,
        max_length=MAX_ASSETS,
    )
    count: CountInterval = (4, 12)
    scale: ScaleInterval = (0.7, 1.4)


class Terrain(SpecModel):
    styles: list[TerrainStyle] = Field(
        default_factory=lambda: ["sand", "pebbles", "rock"], min_length=1, max_length=MAX_CHOICES
    )
    variants: StrictInt = Field(8, ge=1, le=MAX_VARIANTS)
    size_m: StrictFloat = Field(12.0, gt=0, le=1000)
    cells: StrictInt = Field(192, ge=2, le=MAX_TERRAIN_CELLS)
    relief_m: StrictFloat = Field(0.25, ge=0, le=100)
    # User terrain: a mesh file (replaces the procedural heightfield).
    mesh: FileRef | None = None
    # A base colour image (sRGB), applied per pixel and repeated every texture_tile_m: the terrain's colour (it
    # replaces the procedural style's colour and texture).
    texture: FileRef | None = None
    # With texture: its tangent-space normal map (glTF's convention: x right, green towards the image's top).
    normal_map: FileRef | None = None
    # With texture and no normal_map: a grey height map whose full range is height_map_m of relief, made into the
    # normal map.
    height_map: FileRef | None = None
    height_map_m: StrictFloat = Field(0.01, gt=0, le=10)
    # Metres one repeat of the user's texture set spans (procedural textures have their own sizes).
    texture_tile_m: StrictFloat = Field(1.0, gt=0, le=1000)
    # Anti-tiling: the texture coordinates displaced by a smooth noise (up to 0.3 of a repeat, features 8 repeats
    # apart, stretching a texture by under 15%), so a repeated texture does not line up in a grid; free at render
    # time.
    anti_tiling: StrictBool = True
    # The seabed continued beyond the tile out to the camera's far clip (coarser rings, the tile's mean height and
    # colour), so no ray that points down ends in open water at the tile's edge; off: the tile alone.
    far_field: StrictBool = True

    @model_validator(mode="after")
    def _texture_set(self) -> Terrain:
        """normal_map and height_map belong to a texture, and give one normal map: at most one of them."""
        if self.texture is None and (self.normal_map is not None or self.height_map is not None):
            which = "normal_map" if self.normal_map is not None else "height_map"
            raise ValueError(f"{which} needs texture (the base colour image it goes with)")
        if self.normal_map is not None and self.height_map is not None:
            raise ValueError("give normal_map or height_map, not both (a height map is made into the normal map)")
        return self


class Materials(SpecModel):
    """Per-pixel surface detail of the built-in terrains and procedural assets."""

    # Seeded procedural PBR textures (base colour detail, normal map) made at run time, no downloads: each terrain
    # style and procedural family has its own, in `variants` variants of `texture_px` texels a side. Off: vertex
    # colours only, as before 0.7.
    procedural: StrictBool = True
    # Texels a side of each procedural texture (a power of two).
    texture_px: StrictInt = Field(512, ge=64, le=2048)
    # Texture variants of each terrain style and procedural family: a terrain or asset variant v takes texture
    # variant v mod variants.
    variants: StrictInt = Field(4, ge=1, le=64)
    # The anisotropic filter's most taps along a footprint (1: trilinear only): sharper textures on a seabed seen at
    # a grazing angle, at a cost. On one H200 at 1080p the render-only ceiling of the default example keeps 91% of
    # its untextured frames/s at 1, 89% at 2, 78% at 4, 65% at 16 (bench/results/gpu/textures/). Software renderers
    # filter trilinearly whatever is asked (their anisotropic path is ~80x slower).
    anisotropy: Literal[1, 2, 4, 8, 16] = 2

    @field_validator("texture_px")
    @classmethod
    def _power_of_two(cls, v: int) -> int:
        """A power of two (mipmaps halve it down to one texel)."""
        if v & (v - 1):
            raise ValueError(f"{v} is not a power of two (64, 128, ..., 2048)")
        return v


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
