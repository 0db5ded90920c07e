"""Field types every section of the spec shares: the strict base model, intervals and vectors."""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, StrictFloat, WithJsonSchema

MAX_CHOICES = 64  # entries in water.jerlov and terrain.styles (repeats weight the draw)
# Every interval and vector of the spec lies within +-MAX_MAGNITUDE: far beyond any scene (metres, intensities,
# coefficients), and far inside float32, whose range the renderer works in (1e40 overflows it to inf, then NaN).
MAX_MAGNITUDE = 1e6


def bounded(v: tuple[float, ...]) -> tuple[float, ...]:
    if not all(math.isfinite(x) for x in v):
        raise ValueError("bounds must be finite")
    if any(abs(x) > MAX_MAGNITUDE for x in v):
        raise ValueError(f"must lie within +-{MAX_MAGNITUDE:,.0f}")
    return v


def ordered(v: tuple[float, float]) -> tuple[float, float]:
    bounded(v)
    if v[0] > v[1]:
        raise ValueError(f"min {v[0]} > max {v[1]}")
    return v


def nonneg(v: tuple[float, float]) -> tuple[float, float]:
    if v[0] < 0:
        raise ValueError(f"must be >= 0, got min {v[0]}")
    return v


def positive(v: tuple[float, float]) -> tuple[float, float]:
    if v[0] <= 0:
        raise ValueError(f"must be > 0, got min {v[0]}")
    return v


def number_schema(**bounds: float) -> WithJsonSchema:
    """The JSON schema of a number with these JSON Schema bounds (minimum=, exclusiveMinimum=, ...): what a validator
    of the tuple holding it checks, stated in the spec's JSON schema (the API's OpenAPI document) as well."""
    return WithJsonSchema({"type": "number", **bounds})


# Each element's bounds follow from its tuple's checks: within +-MAX_MAGNITUDE, and for an ordered interval whose
# min is >= 0 (> 0), so is its max.
Coordinate = Annotated[StrictFloat, number_schema(minimum=-MAX_MAGNITUDE, maximum=MAX_MAGNITUDE)]
NonNegative = Annotated[StrictFloat, number_schema(minimum=0, maximum=MAX_MAGNITUDE)]
Positive = Annotated[StrictFloat, number_schema(exclusiveMinimum=0, maximum=MAX_MAGNITUDE)]

# A closed interval [min, max] written as a two-element list in spec files.
Interval = Annotated[tuple[Coordinate, Coordinate], AfterValidator(ordered)]
NonNegInterval = Annotated[tuple[NonNegative, NonNegative], AfterValidator(ordered), AfterValidator(nonneg)]
PositiveInterval = Annotated[tuple[Positive, Positive], AfterValidator(ordered), AfterValidator(positive)]
Vec3 = Annotated[tuple[Coordinate, Coordinate, Coordinate], AfterValidator(bounded)]


class SpecModel(BaseModel):
    # NaN and inf would slip past every bound check (NaN compares false), so no float field takes them.
    # Integer, float and boolean fields are StrictInt / StrictFloat / StrictBool: true, "7" and 2.0 are not integers,
    # true and "0.5" are not numbers (an integer is a float), 1 and "yes"
    # are not booleans (YAML's own true/false and JSON's true/false are).
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def within(v: tuple[float, float], lo: float, hi: float) -> tuple[float, float]:
    if v[0] < lo or v[1] > hi:
        raise ValueError(f"must lie within [{lo}, {hi}]")
    return v
