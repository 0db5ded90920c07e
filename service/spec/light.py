"""The spec's light and water: the sun and sky, lamps on the vehicle, caustics, and the water's description."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, StrictBool, StrictFloat, field_validator, model_validator

from seasynth.service.spec.types import MAX_CHOICES, Interval, NonNegInterval, PositiveInterval, SpecModel, Vec3, within
from seasynth.service.water import JERLOV_TYPES

MAX_LAMPS = 4


class Lamp(SpecModel):
    """A spot light fixed to the camera (KITTI camera axes: x right, y down, z forward; metres).

    Its profile is the path tracer's (Mitsuba's `spot`): full intensity within beam_width_deg of its axis, then
    falling linearly in angle to 0 at cutoff_deg. intensity x colour is its radiant intensity on the axis, in the
    units of lighting.sun_intensity per steradian (a surface 1 m away, facing the lamp, gets that irradiance).
    """

    offset_m: Vec3 = (0.0, 0.0, 0.0)
    direction: Vec3 = (0.0, 0.0, 1.0)
    beam_width_deg: StrictFloat = Field(20.0, gt=0, lt=90)
    cutoff_deg: StrictFloat = Field(35.0, gt=0, lt=90)
    colour: Vec3 = (1.0, 1.0, 1.0)
    intensity: NonNegInterval = (4.0, 4.0)

    @model_validator(mode="after")
    def _check(self) -> Lamp:
        if math.hypot(*self.direction) < 1e-6:
            raise ValueError("direction must not be the zero vector")
        if self.beam_width_deg > self.cutoff_deg:
            raise ValueError(f"beam_width_deg {self.beam_width_deg} > cutoff_deg {self.cutoff_deg}")
        if min(self.colour) < 0:
            raise ValueError(f"colour must be >= 0 per channel, got {list(self.colour)}")
        return self


class Caustics(SpecModel):
    """The sun's beam focused by surface waves (water.model physical; worker/light/caustics.py states the model).
    Off by default. The waves' wavelength (m) and rms slope are drawn per frame."""

    enabled: StrictBool = False
    wavelength_m: PositiveInterval = (0.3, 1.0)
    slope: Annotated[PositiveInterval, AfterValidator(lambda v: within(v, 0, 1))] = (0.05, 0.15)


class Lighting(SpecModel):
    # Elevation above the horizon, in air; at or below 0 the sun is down and its term is not rendered.
    sun_elevation_deg: Annotated[Interval, AfterValidator(lambda v: within(v, -90, 90))] = (45.0, 85.0)
    sun_azimuth_deg: Annotated[Interval, AfterValidator(lambda v: within(v, -360, 360))] = (0.0, 360.0)
    sun_intensity: NonNegInterval = (0.8, 1.6)
    # Sky light: the irradiance it gives a horizontal surface just below the water surface (with water.model
    # paper: a constant term, in air).
    ambient: NonNegInterval = (0.15, 0.35)
    # Sun shadows (a shadow map) with water.model physical; lamps always cast shadows there.
    shadows: StrictBool = True
    caustics: Caustics = Caustics()
    lamps: list[Lamp] = Field(default_factory=list, max_length=MAX_LAMPS)


class RGBInterval(SpecModel):
    """Per-channel intervals: each of R, G, B drawn independently in [min_c, max_c]."""

    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _check(self) -> RGBInterval:
        for c, lo, hi in zip("RGB", self.min, self.max):
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"channel {c} bounds must be finite")
            if lo < 0:
                raise ValueError(f"channel {c}: must be >= 0, got {lo}")
            if lo > hi:
                raise ValueError(f"channel {c}: min {lo} > max {hi}")
        return self


class Particles(SpecModel):
    """Marine snow: suspended aggregates drawn as small spheres in the volume the camera sees, lit and attenuated
    like every surface, never labelled but hiding what lies behind them (docs/optics.md#marine-snow). Off by
    default."""

    enabled: StrictBool = False
    # Particles per cubic metre with a diameter in diameter_mm, drawn per frame; unset: the range of the frame's
    # Jerlov type (seasynth.service.water.MARINE_SNOW_PER_M3).
    density_per_m3: Annotated[NonNegInterval, AfterValidator(lambda v: within(v, 0, 1e5))] | None = None
    # The smallest and largest diameter (mm); 0.5 mm is marine snow's usual lower bound.
    diameter_mm: Annotated[PositiveInterval, AfterValidator(lambda v: within(v, 0, 100))] = (0.5, 5.0)
    # Diameters follow a power law n(d) ~ d^-size_slope per unit diameter between diameter_mm's bounds (4: Junge's
    # cumulative N(>d) ~ d^-3).
    size_slope: StrictFloat = Field(4.0, ge=0, le=8)
    # Each particle's diffuse albedo (linear, the same in R, G and B), drawn uniformly in this range.
    albedo: Annotated[NonNegInterval, AfterValidator(lambda v: within(v, 0, 1))] = (0.4, 0.7)


WaterModel = Literal["physical", "paper"]
_PAPER_FIELDS = ("beta_D", "beta_B", "B_inf")
# Fields only the paper's model reads: a spec giving any of them and no model was written for that model.
PAPER_ONLY_FIELDS = (*_PAPER_FIELDS, "backscatter_ratio", "B_inf_jitter")
_PHYSICAL_FIELDS = ("absorption", "scattering")


class Water(SpecModel):
    """Water: one physical description (absorption, scattering, phase function, depth) from which every light term
    is derived (model physical), or the paper's deferred model with its three coefficients (model paper).

    model unset: physical, unless the section gives a field only the paper's model reads (beta_D, beta_B, B_inf,
    backscatter_ratio, B_inf_jitter): such a section was written for the paper's model and keeps it. A whole spec
    also keeps the paper's model where the physical one would reject it (DatasetSpec: a camera reaching the default
    seabed depth), and records the model it resolved, so a spec's canonical form always names its model.
    """

    enabled: StrictBool = True
    model: WaterModel | None = None
    jerlov: list[str] = Field(default_factory=lambda: ["II", "III", "3C", "5C"], max_length=MAX_CHOICES,
                              json_schema_extra={"items": {"type": "string", "enum": list(JERLOV_TYPES)}})
    # Multiplies a type's coefficients per frame (physical: a and b together; paper: beta_D).
    beta_jitter: Annotated[PositiveInterval, AfterValidator(lambda v: within(v, 0, 100))] = (0.85, 1.15)
    # Physical: explicit per-channel absorption a and scattering b (1/m), instead of the Jerlov types' values.
    absorption: RGBInterval | None = None
    scattering: RGBInterval | None = None
    # Henyey-Greenstein asymmetry of the phase function (0.92: Petzold's average particle, b_b/b ~ 0.018).
    phase_g: Annotated[Interval, AfterValidator(lambda v: within(v, 0.0, 0.99))] = (0.92, 0.92)
    # Depth of the seabed (world z = 0) below the water surface, metres; the camera's depth follows.
    depth_m: Annotated[PositiveInterval, AfterValidator(lambda v: within(v, 0, 11000))] = (5.0, 20.0)
    # beta_B = ratio * beta_D per channel when beta_B is not given explicitly.
    backscatter_ratio: PositiveInterval = (0.8, 1.0)
    beta_D: RGBInterval | None = None
    beta_B: RGBInterval | None = None
    B_inf: RGBInterval | None = None
    # Multiplies each type's default veiling light per frame (when B_inf is not given).
    B_inf_jitter: PositiveInterval = (0.8, 1.2)
    # Spread the surfaces' forward-scattered light by its point spread function (seasynth.worker.optics
    # .forward_scatter); physical model only.
    forward_scatter: StrictBool = False
    # The sun's and the sky's light along view rays and on surfaces from the solved water column
    # (seasynth.worker.light.solved, docs/light.md); off: today's closed form through K (0.10 and before). Physical
    # model only: the paper's model and water that is off ignore it, so that every spec's dump (where it is true by
    # default) reads back as the spec it came from.
    solved_column: StrictBool = True
    particles: Particles = Particles()

    @field_validator("jerlov")
    @classmethod
    def _known_types(cls, v: list[str]) -> list[str]:
        for name in v:
            if name not in JERLOV_TYPES:
                raise ValueError(f"unknown Jerlov type {name!r}; known: {', '.join(JERLOV_TYPES)}")
        return v

    @property
    def resolved_model(self) -> str:
        """The model frames use: `model`, else paper if a paper-only field is given, else physical."""
        if self.model is not None:
            return self.model
        return "paper" if self.model_fields_set.intersection(PAPER_ONLY_FIELDS) else "physical"

    @model_validator(mode="after")
    def _described(self) -> Water:
        model = self.resolved_model
        wrong = _PHYSICAL_FIELDS if model == "paper" else _PAPER_FIELDS
        for name in wrong:
            if getattr(self, name) is not None:
                how = "is" if self.model is not None else "resolves to (unset, with paper-only fields given)"
                raise ValueError(f"{name} belongs to the {'physical' if model == 'paper' else 'paper'} model, "
                                 f"but water.model {how} {model}")
        if self.forward_scatter and not (self.enabled and model == "physical"):
            raise ValueError("forward_scatter spreads light the physical model scatters; it needs water.enabled: "
                             f"true and water.model: physical (got enabled {self.enabled}, model {model})")
        self._particles_described(model)
        if not self.enabled or self.jerlov:
            return self
        if model == "paper" and (self.beta_D is None or self.B_inf is None):
            raise ValueError("with no jerlov types, give beta_D and B_inf explicitly")
        if model == "physical" and (self.absorption is None or self.scattering is None):
            raise ValueError("with no jerlov types, give absorption and scattering explicitly")
        return self

    def _particles_described(self, model: str) -> None:
        p = self.particles
        if not p.enabled:
            return
        if not self.enabled:
            raise ValueError("particles: marine snow lives in the water; set water.enabled: true")
        explicit = ("absorption", "scattering") if model == "physical" else ("beta_D", "B_inf")
        typed = self.jerlov and any(getattr(self, name) is None for name in explicit)
        if p.density_per_m3 is None and not typed:
            raise ValueError("particles.density_per_m3: give it when the water has no Jerlov type to take it from "
                             f"(water.jerlov empty, or {' and '.join(explicit)} given)")
