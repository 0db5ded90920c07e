"""The lens, exposure and sensor sections of the spec (seasynth.worker.optics): every field off by default."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StrictFloat, model_validator

from seasynth.service.spec.types import NonNegInterval, SpecModel, number_schema

Multiplier = Annotated[StrictFloat, Field(gt=0, le=100), number_schema(exclusiveMinimum=0, maximum=100)]


class Lens(SpecModel):
    """The camera's lens and exposure, shared by `camera` (seasynth.service.spec.scene.Camera)."""

    # Depth of field: the f-number of a thin lens focused at focus_m; None: a pinhole (everything sharp).
    aperture_f: StrictFloat | None = Field(None, ge=0.5, le=128)
    focus_m: StrictFloat = Field(2.0, ge=0.01, le=1e4)  # z-distance (along the optical axis) in focus, metres
    # The sensor's width: with K it fixes the focal length, fx (pixels) * sensor_width_mm / 1000 / width metres
    # (6.17 mm: a 1/2.3" sensor, as in action cameras in housings).
    sensor_width_mm: StrictFloat = Field(6.17, gt=0, le=100)
    # Natural vignetting: irradiance falls as cos(field angle)^(4 strength) (1: the thin lens's cos^4 law; 0: none).
    vignetting: StrictFloat = Field(0.0, ge=0, le=8)
    # Motion blur: the shutter stays open exposure_s seconds, centred on the frame's time.
    exposure_s: StrictFloat = Field(0.0, ge=0, le=1)
    # A rolling shutter: rows are read top to bottom over readout_s seconds (0: a global shutter).
    readout_s: StrictFloat = Field(0.0, ge=0, le=1)
    # For `random` trajectories (a survey's frames take the trajectory's velocity): the vehicle's speed over the
    # exposure, drawn per frame in a uniformly drawn direction (the frame's motion stream).
    velocity_m_s: NonNegInterval = (0.0, 0.0)
    # For `random` trajectories: the vehicle's turn rate over the exposure, drawn per frame about a uniform axis.
    angular_rate_deg_s: NonNegInterval = (0.0, 0.0)

    def focal_length_m(self, fx_px: float, width: int) -> float:
        return fx_px * self.sensor_width_mm / 1000.0 / width

    def check_focus(self, fx_px: float, width: int) -> None:
        """A thin lens images only objects beyond its focal length: refuse a focus distance at or inside it."""
        f = self.focal_length_m(fx_px, width)
        if self.aperture_f is not None and self.focus_m <= f:
            raise ValueError(f"focus_m {self.focus_m} m is at or inside the focal length {f:.4g} m "
                             f"(fx {fx_px:.4g} px x sensor_width_mm {self.sensor_width_mm} / width {width} px)")


class Noise(SpecModel):
    """The sensor: off by default; recorded in meta when on. In order: exposure (exposure_ev or auto_exposure) and
    gain, photon noise, read noise and gaussian_sigma, white balance, clip to the full well."""

    gaussian_sigma: StrictFloat = Field(0.0, ge=0, le=0.5)  # additive, linear light (meta's "noise")
    # Electrons at a linear value of 1 at gain 1 (None: no photon or read noise). At gain g a value of 1 is
    # full_well_e / g electrons: photon noise has variance value * g / full_well_e.
    full_well_e: StrictFloat | None = Field(None, ge=1, le=1e7)
    read_noise_e: StrictFloat = Field(0.0, ge=0, le=1e4)  # electrons RMS, amplified by the gain like the signal
    gain: StrictFloat = Field(1.0, gt=0, le=1000)  # analog gain, after the light is collected
    exposure_ev: StrictFloat = Field(0.0, ge=-20, le=20)  # fixed: the light scaled by 2^ev
    # Automatic: the scale that brings the mean of the recorded image (all pixels and channels, clipped at 1,
    # before noise) to this target; replaces exposure_ev.
    auto_exposure: StrictFloat | None = Field(None, gt=0, lt=1)
    # Per-channel multipliers (R, G, B), or "gray_world": the ones that make the exposed image's channel means
    # equal (their mean kept).
    white_balance: tuple[Multiplier, Multiplier, Multiplier] | Literal["gray_world"] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> Noise:
        """`read_noise_e` needs `full_well_e`; `exposure_ev` and `auto_exposure` are not both given."""
        if self.read_noise_e > 0 and self.full_well_e is None:
            raise ValueError("read_noise_e is in electrons: give full_well_e too")
        if self.auto_exposure is not None and self.exposure_ev != 0:
            raise ValueError("give either exposure_ev or auto_exposure, not both")
        return self

    @property
    def sensor_on(self) -> bool:
        """Anything beyond gaussian_sigma."""
        return (self.full_well_e is not None or self.gain != 1 or self.exposure_ev != 0
                or self.auto_exposure is not None or self.white_balance is not None)
