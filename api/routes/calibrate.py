"""Water calibration: estimate the water of an uploaded photo (and its range map) and answer a spec water: section.
Needs no Redis or bucket: the estimate is computed here from the upload (numpy and Pillow only)."""

import uuid
from typing import Annotated, Literal

from fastapi import APIRouter, File, Query, UploadFile

from seasynth.api.models import UPLOAD_RULES, CalibrationPublic, WaterEstimatePublic, error_responses, file_names
from seasynth.api.slots import RenderGate
from seasynth.service.calibration.estimate import WaterEstimate
from seasynth.service.calibration.io import RANGE_FORMATS, estimate_files
from seasynth.service.calibration.output import to_spec_water

router = APIRouter(tags=["calibration"])
# An estimate takes 0.4-3.5 s of one core (bench/results/cpu/calibration.md): at most this many run at once in an
# API process, so calibrations cannot starve its status reads; one that finds no slot within the wait gets 503
# with Retry-After.
CALIBRATION_SLOTS = 1
CALIBRATION_WAIT_S = 10.0
GATE = RenderGate(CALIBRATION_SLOTS, CALIBRATION_WAIT_S, busy="the API is busy with other calibrations; try again "
                  "shortly")


def estimate_public(e: WaterEstimate) -> WaterEstimatePublic:
    fields: dict = {}
    for key, c in (("beta_D", e.beta_D), ("beta_B", e.beta_B), ("B_inf", e.B_inf), ("beta_D_ratio", e.beta_D_ratio),
                   ("beta_B_ratio", e.beta_B_ratio), ("a", e.absorption), ("b", e.scattering)):
        fields[key], fields[f"{key}_sd"] = list(c.value), list(c.sigma)
        if key not in ("a", "b"):
            fields[f"{key}_identified"] = list(c.identified)
    return WaterEstimatePublic(
        **fields, nearest_jerlov=e.nearest_jerlov, with_range=e.with_range, method=e.method, notes=list(e.notes),
        pixels_used=e.pixels_used, open_water_pixels=e.open_water_pixels,
        range_span_m=None if e.range_span_m is None else list(e.range_span_m), bootstrap=e.bootstrap, seed=e.seed)


# depth's schema is a file, not a file or null: a part named depth is a file; leave the part out for none.
DEPTH = file_names(depth=(tuple(RANGE_FORMATS), "range.npy"))
DEPTH_DOC = ("Its range map (optional), the photo's size; its file name's suffix sets the format: "
             + "; ".join(f"{k} {v}" for k, v in RANGE_FORMATS.items()))
REFUSED = f"{UPLOAD_RULES}: the photo an 8-bit image, the range map one of the photo's size"


@router.post("/calibrate", response_model=CalibrationPublic, openapi_extra=DEPTH,
             responses=error_responses(400, 401, 413, 422, 503, why={422: REFUSED}))
async def calibrate(
    photo: Annotated[UploadFile, File(description="The photo: 8-bit sRGB PNG or JPEG")],
    depth: Annotated[UploadFile, File(description=DEPTH_DOC)] = None,
    range_spread: Annotated[float, Query(ge=0.0, lt=1.0, description="Relative half-width of each coefficient's "
                                         "range in the answered water section (0: fixed water)")] = 0.1,
    prior: Annotated[Literal["jerlov", "none"] | None, Query(
        description="With a range map: jerlov (the default when absent: beta_D from the Jerlov family and one "
                    "beta_B/beta_D ratio for all channels, the water the generator renders; biased off it) or none "
                    "(each channel fitted freely)")] = None,
) -> CalibrationPublic:
    """Estimate the water of an underwater photo (multipart field `photo`, 8-bit sRGB PNG or JPEG), optionally with a
    range map of the same size (field `depth`; its file name's suffix gives the format: .png 16-bit millimetres,
    .npy or .tif float metres, range along the line of sight). Without a range map only B_inf and the channel
    ratios of beta_B can be estimated; the answer says what was not identified."""
    photo_bytes = await photo.read()
    depth_bytes = None if depth is None else await depth.read()

    def run() -> CalibrationPublic:
        estimate = estimate_files(photo_bytes, photo.filename or "photo", depth_bytes,
                                  (depth and depth.filename) or "depth", prior=prior)
        return CalibrationPublic(estimate=estimate_public(estimate), water=to_spec_water(estimate, spread=range_spread))

    return await GATE.run(uuid.uuid4().hex, run)  # a fresh client token: calibrations queue, none supersedes another
