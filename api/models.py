"""Pydantic models at the HTTP edge: what the API answers (requests take the DatasetSpec itself)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from seasynth.service.records.store import ERRORS_SHOWN


class DatasetLinks(BaseModel):
    self: str
    manifest: str
    frames: str = Field(description="Template: replace {index} with a frame index")


class DatasetCreated(BaseModel):
    id: str
    state: str
    frames_total: int
    shards_total: int
    code_version: str
    links: DatasetLinks


class ShardErrorPublic(BaseModel):
    shard: int
    error: str


class DatasetPublic(BaseModel):
    id: str
    state: str = Field(description="queued, running, succeeded, failed or cancelled")
    frames_done: int = Field(description="Sum of frame_count over committed shards (a retry never counts twice)")
    frames_total: int
    shards_done: int
    shards_failed: int
    shards_total: int
    shard_size: int
    attempts: int = Field(description="Shard task executions started, retries included")
    frames_per_s: float | None
    eta_s: float | None
    errors: list[ShardErrorPublic] = Field(
        description=f"Errors of the failed shards with the lowest indices, at most {ERRORS_SHOWN} (shards_failed "
        "counts them all)"
    )
    seed: int
    code_version: str
    renderer: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    purged: bool
    restored_at: datetime | None = Field(
        None, description="When this record was rebuilt from the bucket after Redis lost its data: the committed "
        "shards and the state are back, the attempts, errors and timings from before are not")
    notice: str | None = Field(
        None, description="Why the dataset is not progressing, where a worker knows: its shards wait for a worker "
        "running the renderer they were started with (how long, how many hand-backs), or gave up on one")
    links: DatasetLinks


class DatasetList(BaseModel):
    items: list[DatasetPublic]
    total: int
    offset: int
    limit: int
    next: str | None


class ManifestExportPart(BaseModel):
    key: str = Field(description="Object key in the bucket: an uncompressed tar")
    sha256: str = Field(description="Lowercase hex sha256 of the whole object")
    bytes: int
    url: str = Field(description="Presigned GET URL (expires)")


class ManifestShard(BaseModel):
    index: int
    key: str = Field(description="Object key in the bucket")
    first_frame: int
    frame_count: int
    sha256: str = Field(description="Lowercase hex sha256 of the whole object")
    bytes: int
    renderer: str
    url: str = Field(description="Presigned GET URL (expires)")
    exports: dict[str, ManifestExportPart] = Field(
        default_factory=dict,
        description="The shard's part of each export format its spec switches on (outputs.coco, yolo, mcap): "
        "that format's files for the shard's frames, which `seasynth fetch --format` merges",
    )


class ManifestPublic(BaseModel):
    """One page of the manifest: the committed shards with index in [start, start + limit)."""

    format: str
    id: str
    state: str
    complete: bool = Field(description="Every shard is committed (all pages together list shards_total shards)")
    frames_total: int
    frames_done: int = Field(description="Frames in committed shards, over all pages")
    shards_total: int
    shards_done: int = Field(description="Committed shards, over all pages")
    seed: int
    code_version: str
    renderer: str | None
    spec: dict[str, Any]
    start: int = Field(description="First shard index this page covers")
    limit: int = Field(description="Shard indices this page covers")
    next: str | None = Field(description="The next page (same limit), or null on the last page")
    urls_expire_s: int | None = Field(
        description="Seconds each url of this page stays valid from this answer (SEASYNTH_PRESIGN_EXPIRY_S, "
        "60 s to 7 days; ask for the page again for fresh ones); null where urls do not expire (local storage)")
    shards: list[ManifestShard] = Field(description="The committed shards of this page, in shard order")


class AssetPublic(BaseModel):
    asset_id: str = Field(description="sha256 of the file; reference it as {\"asset_id\": ...} in a spec")
    filename: str = Field(description="The name these bytes were first uploaded under (its suffix sets the format)")
    bytes: int
    format: str = Field(description="glb, obj, ply, stl, zip (meshes; a zip holds a textured glTF or OBJ with its "
                        "files), png or jpeg (images)")
    kind: str = Field(description="mesh (targets, distractors, terrain.mesh) or image (terrain.texture, normal_map, height_map)")


class AssetListed(AssetPublic):
    uploaded_at: datetime | None = Field(description="When these bytes were first uploaded (null where the object "
                                         "store keeps no time)")
    thumbnail: str | None = Field(description="A mesh's picture (PNG, 128x96): GET it with the key; null for images")


class AssetList(BaseModel):
    items: list[AssetListed] = Field(description="Uploaded assets, newest first")
    total: int
    offset: int
    limit: int
    next: str | None


class Health(BaseModel):
    status: str
    version: str
    checks: dict[str, str] = {}


class ErrorPublic(BaseModel):
    """Every error the API answers, 422 included (not FastAPI's default list of validation objects)."""

    detail: str = Field(description="What went wrong, naming the field, file, limit or dataset at fault")
    errors: list[str] = Field(description="The same, one line per problem")


ERROR_WHY = {
    400: "Malformed request: unparsable JSON, multipart body or Content-Length",
    401: "A valid API key is required (when SEASYNTH_API_KEYS is set)",
    404: "No such dataset (or a deleted one), frame or path",
    409: "Conflicts with the dataset's or asset's current state (the body says which)",
    413: "Over a configured limit (the body names it)",
    422: "Invalid request: each line of `errors` names a field and why",
    502: "The frame worker failed to render it (retrying does not help)",
    503: "A dependency (Redis, the bucket, the broker, a frame worker) is unavailable; retry after Retry-After seconds",
}


# A small spec that every operation taking one accepts: the OpenAPI document's example (Swagger UI fills it in, and
# Schemathesis's examples phase sends it).
SPEC_EXAMPLE: dict[str, Any] = {"seed": 7, "frames": 24, "shard_size": 8, "camera": {"width": 160, "height": 120},
                                "targets": {"assets": [{"procedural": "urchin"}], "count": [2, 4]}}

# What a schema-valid request can still be refused for (422): rules JSON Schema cannot state, each named in the
# description of the 422 its operation declares.
SPEC_RULES = (
    "Invalid request: each line of `errors` names a field and why. Besides what this schema states, a spec keeps "
    "the rules between its fields that JSON Schema cannot (docs/spec.md lists each model's checks across fields): "
    "every range's min <= max, the camera and vehicle under the water surface, lamps and caustics only with the "
    "physical light model, a shard within 600 megapixels, the sonar's render and fan within their pixel budgets, "
    "among others; integers are strict, so `2.0` is refused where the schema says integer (JSON Schema counts it as "
    "one); and the service takes files by the asset_id of an uploaded asset of the kind the field needs, not by path"
)
UPLOAD_RULES = (
    "Invalid request: each line of `errors` names a field or file and why. Besides what this schema states, each "
    "file must decode as its format"
)


def error_responses(*codes: int, why: dict[int, str] | None = None) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for these error statuses, each with the one error body model; `why` gives an
    operation's own description of a status (what it refuses with it that its schema cannot state)."""
    why = why or {}
    return {code: {"model": ErrorPublic, "description": why.get(code, ERROR_WHY[code])} for code in codes}


def file_names(**parts: tuple[tuple[str, ...], str]) -> dict[str, Any]:
    """A route's openapi_extra stating, per multipart file field, the suffixes its file name must end in (any case),
    as the OpenAPI encoding object's Content-Disposition header: {field: (suffixes, an example name)}."""

    def anycase(suffix: str) -> str:
        return "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else f"\\{c}" for c in suffix)

    encoding = {
        field: {"headers": {"Content-Disposition": {
            "description": f"The part's file name ends in one of {', '.join(suffixes)}: its suffix sets the format",
            "required": True,
            "schema": {"type": "string", "pattern": f'filename="[^"]*(?:{"|".join(map(anycase, suffixes))})"'},
            "example": f'form-data; name="{field}"; filename="{example}"',
        }}}
        for field, (suffixes, example) in parts.items()
    }
    return {"requestBody": {"content": {"multipart/form-data": {"encoding": encoding}}}}


RGBOrNone = list[float | None]


class WaterEstimatePublic(BaseModel):
    """A water estimate: per coefficient its (R, G, B) value, 1-sigma (`_sd`) and which channels are identified
    (`_identified`); a value and its sigma are null in a channel where it is not identified."""

    beta_D: RGBOrNone = Field(description="Direct attenuation, 1/m (identified only with a range map)")
    beta_D_sd: RGBOrNone
    beta_D_identified: list[bool]
    beta_B: RGBOrNone = Field(description="Backscatter coefficient, 1/m (identified only with a range map)")
    beta_B_sd: RGBOrNone
    beta_B_identified: list[bool]
    B_inf: RGBOrNone = Field(description="Veiling light, linear RGB")
    B_inf_sd: RGBOrNone
    B_inf_identified: list[bool]
    beta_D_ratio: RGBOrNone = Field(description="beta_D per channel over green's")
    beta_D_ratio_sd: RGBOrNone
    beta_D_ratio_identified: list[bool]
    beta_B_ratio: RGBOrNone = Field(description="beta_B per channel over green's")
    beta_B_ratio_sd: RGBOrNone
    beta_B_ratio_identified: list[bool]
    a: RGBOrNone = Field(description="Absorption, 1/m: not separable from one photo (always null)")
    a_sd: RGBOrNone
    b: RGBOrNone = Field(description="Scattering, 1/m: not separable from one photo (always null)")
    b_sd: RGBOrNone
    nearest_jerlov: str | None
    with_range: bool
    method: str
    notes: list[str] = Field(description="What could not be identified, and why")
    pixels_used: int
    open_water_pixels: int
    range_span_m: list[float] | None
    bootstrap: int
    seed: int


class CalibrationPublic(BaseModel):
    estimate: WaterEstimatePublic
    water: dict[str, Any] = Field(description="A spec water: section (paper model) built from the estimate")
