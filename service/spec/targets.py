"""The spec's targets: the classes a dataset labels, each with its assets, counts, scales and placement."""

from __future__ import annotations

import unicodedata
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BeforeValidator, Field, StrictFloat, StrictInt, model_validator

from seasynth.service.spec.scene import (
    MAX_ASSETS,
    MAX_OBJECTS,
    AssetRef,
    CountInterval,
    ScaleInterval,
)
from seasynth.service.spec.types import Interval, NonNegInterval, PositiveInterval, SpecModel, within

MAX_CLASSES = 64  # classes in targets; the semantic image (outputs.semantic) stores class ids in 8 bits
DONT_CARE = "DontCare"  # KITTI's type of a region to ignore (labels.min_visible_*): no class may take the name

UnitInterval = Annotated[Interval, AfterValidator(lambda v: within(v, 0, 1))]
AngleInterval = Annotated[Interval, AfterValidator(lambda v: within(v, -360, 360))]


def _kitti_token(name: str) -> str:
    """A class name is written as one KITTI label field, and label files are read back with str.split(): refuse any
    character str.isspace() calls whitespace (the pattern's \\S misses U+001C..U+001F) and control characters."""
    bad = next((c for c in name if c.isspace() or unicodedata.category(c) == "Cc"), None)
    if bad is not None:
        raise ValueError(f"{name!r} holds U+{ord(bad):04X}, a whitespace or control character; a class name must be "
                         "one KITTI label field")
    if name == DONT_CARE:
        raise ValueError(f"{DONT_CARE!r} is KITTI's type of the regions to ignore (labels.min_visible_px, "
                         "min_visible_fraction); choose another class name")
    return name


class Seabed(SpecModel):
    """Resting on the seabed: the object's base on a terrain vertex, upright along the seabed's normal there, at a
    random yaw."""

    # `placement: seabed` is short for `placement: {kind: seabed}` (and so for every kind).
    kind: Literal["seabed"]


class Buried(SpecModel):
    """Partly sunk into the seabed (debris, half-buried shells): placed as on the seabed, then moved down along
    the seabed's normal by a drawn fraction of its height."""

    kind: Literal["buried"]
    # Fraction of the object's height (its extent along its own z axis, as scaled) below its resting pose.
    sunk_fraction: UnitInterval = (0.2, 0.6)


class School(SpecModel):
    """Individuals of one class swimming together: one heading and height for the school, each individual at
    spacing_m (drawn per school) from the one placed before it, in the horizontal plane."""

    # Individuals per school; targets.count then counts schools.
    size: CountInterval = (3, 6)
    # Metres between an individual's footprint and its neighbour's (clear of each other; see the spec guide).
    spacing_m: PositiveInterval = (0.05, 0.2)
    # Each individual's yaw differs from the school's heading by up to this (degrees, either way).
    heading_jitter_deg: StrictFloat = Field(10.0, ge=0, le=180)


class InWater(SpecModel):
    """In the water column (fish, jellyfish): above the seabed, at any orientation in the ranges."""

    kind: Literal["water"]
    # Metres between the object's lowest point and the highest seabed under it, drawn per object.
    height_m: NonNegInterval = (0.1, 1.0)
    # Rotation about the world's vertical axis (degrees), then pitch about the object's y and roll about its x.
    yaw_deg: AngleInterval = (0.0, 360.0)
    pitch_deg: AngleInterval = (-15.0, 15.0)
    roll_deg: AngleInterval = (-10.0, 10.0)
    # Optional: place the class in schools (count counts schools).
    school: School | None = None


def _placement_name(v: Any) -> Any:
    """A placement may be written by its kind alone: `placement: water` is `placement: {kind: water}`."""
    return {"kind": v} if isinstance(v, str) else v


Placement = Annotated[Seabed | Buried | InWater, Field(discriminator="kind"), BeforeValidator(_placement_name)]


class Targets(SpecModel):
    """One class of target: what KITTI's `type`, COCO's categories, YOLO's names and MCAP's detections call it,
    the assets its objects are drawn from, how many a frame has, their scales and where they are placed."""

    class_name: Annotated[str, AfterValidator(_kitti_token)] = Field("Urchin", pattern=r"^\S+$", max_length=64)
    assets: list[AssetRef] = Field(
        default_factory=lambda: [AssetRef(procedural="urchin")], min_length=1, max_length=MAX_ASSETS
    )
    # Objects per frame, drawn per frame and class (schools per frame with placement.school).
    count: CountInterval = (3, 8)
    scale: ScaleInterval = (0.8, 1.25)
    placement: Placement = Seabed(kind="seabed")

    def most_objects(self) -> int:
        """The most objects of this class a frame may place."""
        school = getattr(self.placement, "school", None)
        return self.count[1] * (1 if school is None else school.size[1])

    @model_validator(mode="after")
    def _schools_fit(self) -> Targets:
        """count's max times placement.school.size's max is at most the object limit per role and frame."""
        if self.most_objects() > MAX_OBJECTS:
            raise ValueError(f"count max {self.count[1]} schools of up to {self.placement.school.size[1]} is "
                             f"{self.most_objects()} objects, over the limit of {MAX_OBJECTS}")
        return self


def _one_class_as_list(v: Any) -> Any:
    """A single class may be written as one mapping (the form before classes): it is a list of that one class."""
    return [v] if isinstance(v, dict) else v


def _classes_fit(classes: list[Targets]) -> list[Targets]:
    """Class names are unique, and the classes' most objects (count maxima, times school sizes) total at most the
    object limit per role and frame."""
    names = [c.class_name for c in classes]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"class names must be unique; {', '.join(map(repr, repeated))} repeated")
    total = sum(c.most_objects() for c in classes)
    if total > MAX_OBJECTS:
        raise ValueError(f"the classes' count maxima add up to {total} targets a frame, over the limit of "
                         f"{MAX_OBJECTS}")
    return classes


def _mapping_or_list(schema: dict) -> None:
    """The JSON schema says what _one_class_as_list accepts: a list of classes, or one class's mapping."""
    listed = dict(schema)
    schema.clear()
    schema["anyOf"] = [listed["items"], listed]


# The classes in the order that numbers them: class i is COCO category i + 1, YOLO class i, semantic id i + 1.
TargetClasses = Annotated[
    list[Targets],
    Field(min_length=1, max_length=MAX_CLASSES, json_schema_extra=_mapping_or_list),
    BeforeValidator(_one_class_as_list),
    AfterValidator(_classes_fit),
]


def legacy_form(dumped: list[dict], classes: list[Targets]) -> list[dict] | dict:
    """The targets as a spec dump writes them: one class placed on the seabed as the single mapping of specs
    written before classes (so their records and digests keep their bytes), else the list."""
    if len(classes) == 1 and isinstance(classes[0].placement, Seabed):
        one = dict(dumped[0])
        one.pop("placement", None)
        return one
    return dumped


class Labels(SpecModel):
    """Which targets are labelled: a target with a visible pixel but fewer than min_visible_px, or a smaller
    visible fraction than min_visible_fraction, is written as a region to ignore (KITTI `DontCare`, a COCO
    `iscrowd: 1` annotation with its mask; YOLO and MCAP leave it out), never dropped silently."""

    # Least visible pixels (the label box's instance pixels) a labelled target has.
    min_visible_px: StrictInt = Field(1, ge=1, le=2**31 - 1)
    # Least visible fraction: its visible pixels over its pixels when rendered alone in the frame (what KITTI's
    # occluded level is judged on; the part outside the image does not count, KITTI's truncated says that).
    min_visible_fraction: StrictFloat = Field(0.0, ge=0, le=1)

    @property
    def filters(self) -> bool:
        """Whether a target with a visible pixel can be turned into a DontCare region."""
        return self.min_visible_px > 1 or self.min_visible_fraction > 0
