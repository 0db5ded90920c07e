"""The camera's housing port and lens distortion (spec `camera.port`, `camera.distortion`): the geometry that bends
a pixel's ray before it reaches the water (seasynth.service.camera_model turns them into rays)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, StrictFloat, model_validator

from seasynth.service.spec.types import SpecModel, Vec3

# Refractive indices a housing meets: air 1.0 inside; water 1.33-1.35; acrylic 1.49, glass 1.47-1.52, sapphire 1.77.
MIN_INDEX = 1.0
MAX_INDEX = 3.0
AIR_INDEX = 1.0  # inside the housing


class Port(SpecModel):
    """The housing's window in front of the lens. kind "none": the lens sees the water directly (a pinhole in
    water, as before); "flat": a plane glass window perpendicular to the optical axis; "dome": a spherical shell.

    Lengths in millimetres. The camera frame is KITTI's (x right, y down, z forward) with the lens's entrance pupil
    (the pinhole) at its origin; air (index 1.0) fills the housing.
    """

    # none: no port; flat: a plane window; dome: a spherical shell.
    kind: Literal["none", "flat", "dome"] = "none"
    # The glass (flat: between its two planes; dome: between its two spheres).
    thickness_mm: StrictFloat = Field(10.0, gt=0, le=200)
    # The glass's refractive index: acrylic 1.49, glass 1.47-1.52, sapphire 1.77.
    glass_index: StrictFloat = Field(1.49, ge=MIN_INDEX, le=MAX_INDEX)
    # The water's refractive index: sea water 1.34, fresh water 1.33 (visible light).
    water_index: StrictFloat = Field(1.34, ge=MIN_INDEX, le=MAX_INDEX)
    # flat: the entrance pupil's distance to the window's inner plane, along the optical axis.
    distance_mm: StrictFloat = Field(20.0, gt=0, le=1000)
    # dome: the outer sphere's radius (the inner one's is radius_mm - thickness_mm).
    radius_mm: StrictFloat = Field(50.0, gt=0, le=1000)
    # dome: the entrance pupil's position relative to the dome's centre (camera axes); [0, 0, 0]: centred, which
    # leaves every ray unbent.
    pupil_offset_mm: Vec3 = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _fits(self) -> Port:
        """A dome's glass is thinner than its radius, and the entrance pupil lies inside its inner sphere."""
        if self.kind == "dome":
            if self.thickness_mm >= self.radius_mm:
                raise ValueError(f"thickness_mm {self.thickness_mm} must be less than radius_mm {self.radius_mm}")
            off = sum(c * c for c in self.pupil_offset_mm) ** 0.5
            if off >= self.radius_mm - self.thickness_mm:
                raise ValueError(f"pupil_offset_mm puts the entrance pupil {off:.4g} mm from the centre, outside "
                                 f"the dome's inner sphere ({self.radius_mm - self.thickness_mm:.4g} mm)")
        return self


# Brown-Conrady coefficients in OpenCV's order [k1, k2, p1, p2, k3]: radial k1, k2, k3 and tangential p1, p2, on
# normalised image coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy).
Distortion = tuple[
    StrictFloat, StrictFloat, StrictFloat, StrictFloat, StrictFloat,
]
MAX_RADIAL = 10.0
MAX_TANGENTIAL = 1.0


def check_distortion(d: tuple[float, float, float, float, float]) -> tuple[float, float, float, float, float]:
    """|k1|, |k2|, |k3| <= 10 and |p1|, |p2| <= 1."""
    k1, k2, p1, p2, k3 = d
    for name, value, bound in (("k1", k1, MAX_RADIAL), ("k2", k2, MAX_RADIAL), ("p1", p1, MAX_TANGENTIAL),
                               ("p2", p2, MAX_TANGENTIAL), ("k3", k3, MAX_RADIAL)):
        if abs(value) > bound:
            raise ValueError(f"{name} {value} must lie within +-{bound}")
    return d


def distortion_folds(d, K, width: int, height: int) -> float | None:
    """The normalised radius where the radial map r (1 + k1 r^2 + k2 r^4 + k3 r^6) stops increasing before its
    value reaches the image's farthest corner (so two rays would meet at one pixel), or None where it increases
    all the way (the map can be inverted over the whole image)."""
    k1, k2, _, _, k3 = d
    (fx, _, cx), (_, fy, cy), _ = K
    corner = max(((u - cx) / fx) ** 2 + ((v - cy) / fy) ** 2
                 for u in (-0.5, width - 0.5) for v in (-0.5, height - 0.5)) ** 0.5
    # margin: the tangential terms move a corner's radius by up to about 3 (|p1| + |p2|) r^2
    reach = corner + 3 * (abs(d[2]) + abs(d[3])) * corner * corner + 1e-6
    r, step = 0.0, reach / 4096
    while True:
        r2 = r * r
        if 1 + 3 * k1 * r2 + 5 * d[1] * r2 * r2 + 7 * k3 * r2 ** 3 <= 0:
            return r
        if r * (1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3) >= reach or r > 4 * reach:
            return None
        r += step
