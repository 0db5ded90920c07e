"""The spec's `sensors:` section: sonar and navigation sensors fixed to the vehicle, each optional and off by default.

The vehicle's body frame is the camera's (KITTI axes: x right, y down, z forward, metres). A sensor's pose in it is
an offset and a pitch (positive tilts its forward axis down) then yaw (positive turns it to starboard, +x). With
every sensor off (the default) a spec's frames are byte-identical to those written before sensors existed.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationInfo,
    field_validator,
    model_validator,
)

from seasynth.service.spec.types import SpecModel, Vec3

BeamPattern = Literal["sinc2", "gaussian"]
MAX_BEAMS = 1024
MAX_RANGE_BINS = 4096
MAX_FLS_RENDER_SIDE = 8192  # the FLS's perspective render (seasynth.worker.sensors.fls) is at most this many pixels a side
MAX_FLS_RENDER_PIXELS = 8_000_000  # and this many in all (~10x the default's), keeping a frame's arrays near 1 GB
FLS_STEPS_PER_BEAM = 3  # render pixels (at the image centre) per min(beam width, beam spacing)
SSS_ANGLE_STEP_DEG = 0.1  # the SSS render's coarsest angle per pixel
SSS_DEPRESSION_SPAN_DEG = (-5.0, 89.0)  # depressions each SSS side renders, below the sensor's horizontal
DVL_BEAMS = 4  # Janus beams, one one-pixel ray cast each
MAX_FLS_RANGE_M = 500.0  # as the SSS's: long-range imaging sonars reach a few hundred metres at low frequency
MAX_FLS_FAN_SIDE = 4096  # the FLS's Cartesian fan image (seasynth.worker.sensors.fan) is at most this many rows
MAX_FLS_FAN_PIXELS = 8_000_000  # and this many pixels (its lookup arrays are ~17 bytes a pixel, as the render's)


def _fls_range(v: tuple[float, float]) -> tuple[float, float]:
    if not 0 < v[0] < v[1] <= MAX_FLS_RANGE_M:
        raise ValueError(f"need 0 < min < max <= {MAX_FLS_RANGE_M:g} m, got [{v[0]}, {v[1]}]")
    return v


FlsRangeM = Annotated[tuple[StrictFloat, StrictFloat], AfterValidator(_fls_range)]


def fan_size(range_m: tuple[float, float], range_bins: int, horizontal_aperture_deg: float,
             fan_height_px: int | None) -> tuple[int, int]:
    """(width, height) pixels of the FLS's Cartesian fan image (seasynth.worker.sensors.fan). Height: fan_height_px, else one
    row per range bin's depth over [0, rmax] (ceil(range_bins * rmax / (rmax - rmin))), at most MAX_FLS_FAN_SIDE
    and at most the height whose fan holds MAX_FLS_FAN_PIXELS. Width: the odd count of square pixels spanning the
    fan's +-rmax sin(H/2) about its apex."""
    rmin, rmax = range_m
    s = math.sin(min(math.radians(horizontal_aperture_deg) / 2, math.pi / 2))
    height = fan_height_px
    if height is None:
        # The width below is at most 2 s h + 3, so (2 s h + 3) h <= MAX_FLS_FAN_PIXELS keeps the fan in the cap.
        fits = int((math.sqrt(9 + 8 * s * MAX_FLS_FAN_PIXELS) - 3) / (4 * s))
        height = min(math.ceil(rmax / ((rmax - rmin) / range_bins)), MAX_FLS_FAN_SIDE, fits)
    ds = rmax / height
    return 2 * math.ceil(rmax * s / ds) + 1, height


class SensorPose(SpecModel):
    """Where a sensor sits on the vehicle: offset (camera axes, metres), then pitch and yaw (degrees)."""

    offset_m: Vec3 = (0.0, 0.0, 0.0)
    pitch_deg: StrictFloat = Field(0.0, ge=-90, le=90)
    yaw_deg: StrictFloat = Field(0.0, ge=-180, le=180)


class Acoustics(SpecModel):
    """Sea water for sound absorption (Francois-Garrison 1982) and sound speed."""

    temperature_c: StrictFloat = Field(10.0, ge=-2, le=35)
    salinity_ppt: StrictFloat = Field(35.0, ge=0, le=45)
    ph: StrictFloat = Field(8.0, ge=6, le=9)


class FLS(SpecModel):
    """A forward-looking multibeam imaging sonar. Defaults of the order of a Blueprint Oculus M750d's 750 kHz mode
    (130 x 20 deg fan, ~1 deg horizontal beams; its datasheet was not re-checked here), with 256 beams rather than
    its 512 to keep frames small. worker/sensors/fls.py states the model."""

    enabled: StrictBool = False
    pose: SensorPose = SensorPose()
    range_m: FlsRangeM = (0.5, 40.0)
    horizontal_aperture_deg: StrictFloat = Field(130.0, ge=1, le=170)
    vertical_aperture_deg: StrictFloat = Field(20.0, ge=1, le=60)
    beams: StrictInt = Field(256, ge=2, le=MAX_BEAMS)
    range_bins: StrictInt = Field(512, ge=2, le=MAX_RANGE_BINS)
    # Horizontal -3 dB width of one beam; the vertical pattern's -3 dB width is the vertical aperture.
    beam_width_deg: StrictFloat = Field(1.0, ge=0.05, le=30)
    beam_pattern: BeamPattern = "sinc2"
    frequency_khz: StrictFloat = Field(750.0, gt=1, le=3000)
    # Backscatter strength (linear, relative to a perfect Lambertian reflector) per role.
    reflectivity_seabed: StrictFloat = Field(0.3, ge=0, le=1)
    reflectivity_target: StrictFloat = Field(1.0, ge=0, le=1)
    reflectivity_distractor: StrictFloat = Field(0.6, ge=0, le=1)
    incidence_exponent: StrictFloat = Field(1.0, ge=0, le=8)  # n in cos^n(incidence)
    gain_db: StrictFloat = Field(0.0, ge=-60, le=100)
    tvg: StrictBool = True  # time-varied gain: multiplies by r^2 10^(2 alpha r / 10), undoing spreading and absorption
    speckle_looks: StrictFloat = Field(1.0, gt=0, le=1e6)  # L of the unit-mean Gamma(L, 1/L) intensity speckle
    speckle: StrictBool = True
    noise_sigma: StrictFloat = Field(0.0, ge=0, le=1)  # additive Gaussian, in output full-scale units (1 = 65535)
    fan_height_px: StrictInt | None = Field(None, ge=8, le=MAX_FLS_FAN_SIDE)  # Cartesian fan rows; None: see fan_size

    @field_validator("fan_height_px")
    @classmethod
    def _fan_fits(cls, v: int | None, info: ValidationInfo) -> int | None:
        d = info.data
        if v is None or not {"range_m", "range_bins", "horizontal_aperture_deg"} <= d.keys():
            return v  # the default height always fits; a bad field above is reported by itself
        w, h = fan_size(d["range_m"], d["range_bins"], d["horizontal_aperture_deg"], v)
        if w * h > MAX_FLS_FAN_PIXELS:
            raise ValueError(f"the fan image would be {w}x{h} pixels, over {MAX_FLS_FAN_PIXELS}; lower fan_height_px "
                             "(or leave it out: the default fits)")
        return v

    @model_validator(mode="after")
    def _beam_narrower_than_fan(self) -> FLS:
        if self.beam_width_deg >= self.horizontal_aperture_deg:
            raise ValueError(f"beam_width_deg {self.beam_width_deg} must be < horizontal_aperture_deg "
                             f"{self.horizontal_aperture_deg}")
        w, h, _ = self.render_size()
        if max(w, h) > MAX_FLS_RENDER_SIDE or w * h > MAX_FLS_RENDER_PIXELS:
            raise ValueError(f"the sonar's render would be {w}x{h} pixels, over {MAX_FLS_RENDER_SIDE} a side or "
                             f"{MAX_FLS_RENDER_PIXELS} in all; widen beam_width_deg, or lower beams, "
                             "horizontal_aperture_deg or vertical_aperture_deg")
        return self

    def render_size(self) -> tuple[int, int, float]:
        """(width, height, focal length in pixels) of the perspective render covering azimuth +-H/2 and elevation
        +-V (twice the vertical -3 dB half-width) at FLS_STEPS_PER_BEAM pixels per beam at the image centre."""
        spacing = self.horizontal_aperture_deg / self.beams
        f = FLS_STEPS_PER_BEAM / math.radians(min(self.beam_width_deg, spacing))
        half_h = math.radians(self.horizontal_aperture_deg / 2)
        y_max = math.tan(math.radians(self.vertical_aperture_deg)) / math.cos(half_h)
        return 2 * math.ceil(f * math.tan(half_h) + 0.5), 2 * math.ceil(f * y_max + 0.5), f

    def fan_size(self) -> tuple[int, int]:
        """(width, height) of the Cartesian fan image: see the module's fan_size."""
        return fan_size(self.range_m, self.range_bins, self.horizontal_aperture_deg, self.fan_height_px)


class DVL(SpecModel):
    """A Doppler velocity log: four Janus beams at `beam_angle_deg` from its downward axis, 45 deg apart from the
    vehicle's axes (Teledyne Pathfinder/Workhorse layout). Velocity in the vehicle frame (m/s), noise Gaussian;
    measured beam ranges are clipped at 0 m (seasynth.worker.sensors.nav)."""

    enabled: StrictBool = False
    pose: SensorPose = SensorPose()
    beam_angle_deg: StrictFloat = Field(30.0, gt=0, lt=80)
    max_range_m: StrictFloat = Field(50.0, gt=0, le=1000)
    velocity_sigma_m_s: StrictFloat = Field(0.002, ge=0, le=1)
    range_sigma_m: StrictFloat = Field(0.01, ge=0, le=10)


class Pressure(SpecModel):
    """A pressure (depth) sensor: absolute pressure, Gaussian noise of `sigma_pa` (Pa)."""

    enabled: StrictBool = False
    pose: SensorPose = SensorPose()
    sigma_pa: StrictFloat = Field(100.0, ge=0, le=1e5)  # 100 Pa ~ 1 cm of water


class IMU(SpecModel):
    """An inertial unit: angular rate (rad/s) and specific force (m/s^2) from the trajectory's analytic derivatives,
    plus a constant bias drawn per dataset and white noise per frame (Gaussian)."""

    enabled: StrictBool = False
    pose: SensorPose = SensorPose()
    gyro_sigma_rad_s: StrictFloat = Field(1e-4, ge=0, le=1)
    accel_sigma_m_s2: StrictFloat = Field(1e-3, ge=0, le=10)
    gyro_bias_sigma_rad_s: StrictFloat = Field(1e-4, ge=0, le=1)
    accel_bias_sigma_m_s2: StrictFloat = Field(1e-2, ge=0, le=10)


class SSS(SpecModel):
    """A side-scan sonar: one ping per frame, port and starboard beams in the sensor's across-track (x, y) plane,
    narrow along track (z), tilted down by depression_deg. Defaults are typical of a 900 kHz towed or hull unit (not
    one datasheet): 0.5 deg horizontal, 50 deg vertical beams, 20 deg depression, 512 bins per side over 20 m."""

    enabled: StrictBool = False
    pose: SensorPose = SensorPose()
    range_m: StrictFloat = Field(20.0, gt=0, le=500)  # slant range of the last bin; bins start at 0
    range_bins: StrictInt = Field(512, ge=2, le=MAX_RANGE_BINS)  # per side
    horizontal_beam_deg: StrictFloat = Field(0.5, ge=0.05, le=10)  # along-track -3 dB width
    vertical_beam_deg: StrictFloat = Field(50.0, gt=1, le=80)  # across-track -3 dB width
    depression_deg: StrictFloat = Field(20.0, ge=0, le=60)  # beam axis below the sensor's horizontal (x) axis
    beam_pattern: BeamPattern = "gaussian"
    frequency_khz: StrictFloat = Field(900.0, gt=1, le=3000)
    reflectivity_seabed: StrictFloat = Field(0.3, ge=0, le=1)
    reflectivity_target: StrictFloat = Field(1.0, ge=0, le=1)
    reflectivity_distractor: StrictFloat = Field(0.6, ge=0, le=1)
    incidence_exponent: StrictFloat = Field(1.0, ge=0, le=8)
    gain_db: StrictFloat = Field(0.0, ge=-60, le=100)
    tvg: StrictBool = True
    speckle_looks: StrictFloat = Field(1.0, gt=0, le=1e6)
    speckle: StrictBool = True
    noise_sigma: StrictFloat = Field(0.0, ge=0, le=1)

    def render_size(self) -> tuple[int, int, float]:
        """(width along track, height across track, focal length in pixels) of one side's perspective render:
        depressions SSS_DEPRESSION_SPAN_DEG at SSS_ANGLE_STEP_DEG or a third of the horizontal beam per pixel (the
        finer), +-2 horizontal beam widths along track."""
        f = 1.0 / math.radians(min(SSS_ANGLE_STEP_DEG, self.horizontal_beam_deg / 3))
        lo, hi = SSS_DEPRESSION_SPAN_DEG
        half_v = math.radians((hi - lo) / 2)
        half_h = 2 * math.radians(self.horizontal_beam_deg)
        return 2 * math.ceil(f * math.tan(half_h) + 0.5), 2 * math.ceil(f * math.tan(half_v) + 0.5), f


class Sensors(SpecModel):
    """Every sensor besides the camera (which stays in `camera:` and is always on)."""

    acoustics: Acoustics = Acoustics()
    fls: FLS = FLS()
    dvl: DVL = DVL()
    pressure: Pressure = Pressure()
    imu: IMU = IMU()
    sss: SSS = SSS()

    @property
    def any_nav(self) -> bool:
        return self.dvl.enabled or self.pressure.enabled or self.imu.enabled

    def enabled_poses(self) -> dict[str, SensorPose]:
        """Each enabled sensor's pose on the vehicle, by its field name (fls, sss, dvl, pressure, imu)."""
        return {name: s.pose for name in ("fls", "sss", "dvl", "pressure", "imu") if (s := getattr(self, name)).enabled}

    @property
    def enabled_count(self) -> int:
        return len(self.enabled_poses())

    def render_pixels(self) -> int:
        """Pixels the enabled sensors render or image per frame, for the shard limits (service.spec,
        seasynth.service.shards): the FLS's one render and its fan image, the SSS's two renders (a side each), the DVL's
        DVL_BEAMS one-pixel ray casts."""
        n = 0
        if self.fls.enabled:
            w, h, _ = self.fls.render_size()
            fw, fh = self.fls.fan_size()
            n += w * h + fw * fh
        if self.sss.enabled:
            w, h, _ = self.sss.render_size()
            n += 2 * w * h
        if self.dvl.enabled:
            n += DVL_BEAMS
        return n


class Trajectory(SpecModel):
    """How the vehicle (camera) moves between frames. `random`: every frame draws its own pose (the default; frames
    are independent, so a velocity is undefined). `lawnmower`: a survey of parallel legs at a fixed altitude, frame i
    at time i / rate_hz, heading along the legs and pitched down by `pitch_deg`: pose(i) is a pure function of
    (spec, i), smooth within a leg (turns are instantaneous: velocity is piecewise constant)."""

    kind: Literal["random", "lawnmower"] = "random"
    start_m: tuple[Annotated[StrictFloat, Field(ge=-1e4, le=1e4)], Annotated[StrictFloat, Field(ge=-1e4, le=1e4)]] = (
        -4.0, -4.0)  # world x, y of the first leg's start
    leg_length_m: StrictFloat = Field(8.0, ge=0.1, le=10_000)
    leg_spacing_m: StrictFloat = Field(1.0, ge=0.01, le=1000)
    legs: StrictInt = Field(8, ge=1, le=10_000)
    altitude_m: StrictFloat = Field(1.5, ge=0.05, le=1000)  # above world z = 0 (the seabed's reference)
    speed_m_s: StrictFloat = Field(0.5, ge=0.01, le=20)
    rate_hz: StrictFloat = Field(2.0, ge=0.01, le=1000)
    pitch_deg: StrictFloat = Field(30.0, ge=0, le=90)  # camera tilt below the horizon
    heave_m: StrictFloat = Field(0.0, ge=0, le=10)  # amplitude of a sinusoidal altitude change along a leg
    heave_period_s: StrictFloat = Field(8.0, ge=0.1, le=1e4)
