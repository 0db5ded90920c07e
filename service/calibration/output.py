"""A water estimate (seasynth.service.calibration.estimate) as users take it: a spec `water:` section, and lines of text."""

from __future__ import annotations

from seasynth.service.calibration.estimate import CHANNELS, Coefficient, WaterEstimate
from seasynth.service.errors import CalibrationError
from seasynth.service.water import jerlov_veiling_light

BACKSCATTER_RATIO_FILL = 0.9  # to_spec_water: beta_B = this * beta_D in a channel whose beta_B is not identified


def _interval(values: list[float], spread: float, top: float = float("inf")) -> dict:
    return {"min": [round(min(max(0.0, v * (1 - spread)), top), 6) for v in values],
            "max": [round(min(max(0.0, v * (1 + spread)), top), 6) for v in values]}


def to_spec_water(estimate: WaterEstimate, spread: float = 0.1) -> dict:
    """A spec `water:` section (paper model) from an estimate: each coefficient drawn per frame within +-spread
    (relative) of its estimate; spread 0 gives fixed water.

    With every beta_D channel identified the section gives beta_D, beta_B and B_inf explicitly (a channel whose
    beta_B is not identified gets BACKSCATTER_RATIO_FILL * its beta_D). Otherwise (no range) the betas come from the
    nearest Jerlov type (II when none is known) with beta_jitter +-spread, and B_inf is explicit. A channel whose
    B_inf is not identified takes that type's default veiling light (seasynth.service.water.jerlov_veiling_light), never 0
    (which would be water without backscatter). B_inf stays within [0, 1].
    """
    if not (isinstance(spread, (int, float)) and 0 <= spread < 1):
        raise CalibrationError(f"spread: need a number in [0, 1), got {spread!r}")
    default = jerlov_veiling_light(estimate.nearest_jerlov or "II")
    b_inf = [float(v) if v is not None else float(d) for v, d in zip(estimate.B_inf.value, default)]
    section: dict = {"enabled": True, "model": "paper", "B_inf": _interval(b_inf, spread, top=1.0)}
    if all(estimate.beta_D.identified):
        bd = [float(v) for v in estimate.beta_D.value]
        bb = [v if v is not None else BACKSCATTER_RATIO_FILL * d for v, d in zip(estimate.beta_B.value, bd)]
        section.update(jerlov=[], beta_D=_interval(bd, spread), beta_B=_interval(bb, spread))
    else:
        section.update(jerlov=[estimate.nearest_jerlov or "II"], beta_jitter=[1 - spread, 1 + spread])
    return section


def describe(estimate: WaterEstimate) -> str:
    """The estimate as lines of text: each coefficient per channel with its 1-sigma, or 'not identified'."""
    def fmt(c: Coefficient) -> str:
        cells = [f"{n} {v:.4g} +- {s:.2g}" if v is not None else f"{n} not identified"
                 for n, v, s in zip(CHANNELS, c.value, c.sigma)]
        return f"  {c.name:<13}({c.unit}): " + ", ".join(cells)

    lines = [f"water estimate ({'with' if estimate.with_range else 'without'} range; {estimate.pixels_used} pixels, "
             f"{estimate.open_water_pixels} of open water"
             + (f"; range {estimate.range_span_m[0]:.3g}-{estimate.range_span_m[1]:.3g} m"
                if estimate.range_span_m else "") + ")"]
    lines += [fmt(c) for c in (estimate.beta_D, estimate.beta_B, estimate.B_inf, estimate.beta_D_ratio,
                               estimate.beta_B_ratio)]
    lines.append(f"  nearest Jerlov type: {estimate.nearest_jerlov or 'none'}")
    lines += [f"  note: {n}" for n in estimate.notes]
    lines.append(f"  method: {estimate.method}")
    return "\n".join(lines)
