"""The scene playground: a static page, and the routes it calls to validate a spec and preview its frames.

Previews come from a Previewer: the service's sends each render to a frames-queue worker (the API has no GL);
`seasynth playground` passes one that renders in its own process. Renders are bounded: each client has at most one
render at a time and the latest request wins (an older one still waiting answers 409), and when every render
slot stays busy for a moment the answer is 503 with Retry-After.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable
from importlib.resources import files
from typing import Annotated, Any, Literal, Protocol, get_args

import yaml
from fastapi import APIRouter, Header, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import BaseModel, ConfigDict, Field, StrictInt, ValidationError

from seasynth.api.models import SPEC_EXAMPLE, SPEC_RULES, error_responses
from seasynth.api.slots import RenderGate
from seasynth.service import __version__
from seasynth.service.errors import NotFound, RenderError, SpecError, Unavailable
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.scene import ProceduralTarget
from seasynth.service.water import JERLOV_TYPES, JERLOV_VEILING_LIGHT

View = Literal["image", "depth", "instance", "clean", "air"]
STATIC = {"app.js": "text/javascript", "classes.js": "text/javascript", "style.css": "text/css"}
KINDS = get_args(ProceduralTarget)
MAX_STRIP = 16


class Previewer(Protocol):
    """Renders for the page; blocking calls, run off the event loop."""

    def preview(self, spec: DatasetSpec, frame: int, views: list[str]) -> dict: ...

    def strip(self, spec: DatasetSpec, first: int, count: int) -> dict: ...


# The spec is the model POST /datasets takes, so the schema states its fields (unknown keys refused) and integers
# are strict (`false` is not frame 0), as the spec's own are.
class PreviewCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"spec": SPEC_EXAMPLE, "frame": 3, "views": ["image", "depth"]}]})
    spec: DatasetSpec = Field(description="The dataset spec, as POST /datasets takes it")
    frame: StrictInt = Field(0, ge=0, le=10**9, description="Frame index, below the spec's frames")
    views: list[View] = Field(["image"], max_length=5, description="Images wanted beside the hazed image")


class StripCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"spec": SPEC_EXAMPLE, "first": 20}]})
    spec: DatasetSpec = Field(description="The dataset spec, as POST /datasets takes it")
    first: StrictInt = Field(0, ge=0, le=10**9, description="First frame index; frames past the spec's last are "
                             "left out (all of them when `first` is: an empty strip)")
    count: StrictInt = Field(8, ge=1, le=MAX_STRIP)


class SpecCheck(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"spec": SPEC_EXAMPLE}]})
    spec: dict[str, Any]


class FieldError(BaseModel):
    loc: list[str | int] = Field(description="Path of the field in the spec, e.g. ['water', 'jerlov', 0]")
    msg: str


class SpecChecked(BaseModel):
    valid: bool
    errors: list[FieldError]
    yaml: str | None = Field(None, description="The spec as YAML, when valid")


class PreviewPublic(BaseModel):
    frame: int
    seed: int
    width: int
    height: int
    images: dict[str, str] = Field(description="View name -> image data URL (PNG; the image view as the spec encodes it)")
    boxes: list[dict[str, Any]] = Field(description="KITTI boxes: class, box [left, top, right, bottom] px, "
                                                    "truncated, occluded")
    render_ms: float


class StripFrame(BaseModel):
    frame: int
    image: str


class StripPublic(BaseModel):
    frames: list[StripFrame]


class PlaygroundConfig(BaseModel):
    mode: Literal["service", "local"]
    version: str
    schema_: dict[str, Any] = Field(alias="schema")
    spec: dict[str, Any] = Field(description="The spec the page starts from")
    jerlov: dict[str, list[float]] = Field(description="Jerlov type -> the colour of its water (linear RGB)")
    kinds: list[str] = Field(description="The procedural kinds, each with a thumbnail at kinds/{kind}.png")


def field_errors(err: ValidationError) -> list[FieldError]:
    return [FieldError(loc=[p for p in e["loc"]], msg=e["msg"]) for e in err.errors(include_url=False)]


def jerlov_colours() -> dict[str, list[float]]:
    """The colour far water takes (its B_inf) per Jerlov type, for the page's swatches."""
    return {name: [round(float(c), 4) for c in JERLOV_VEILING_LIGHT[name]] for name in JERLOV_TYPES}


def playground_router(previewer_of: Callable[[Request], Previewer], *, mode: str, start_spec: dict[str, Any],
                      slots: int, check: Callable[[Request, DatasetSpec], None] | None = None) -> APIRouter:
    """The page and its routes. `check` refuses specs this server cannot render (e.g. local paths in the
    service); `start_spec` is the spec the page opens with."""
    router = APIRouter(prefix="/playground", tags=["playground"], responses=error_responses(401))
    gate = RenderGate(slots)
    page = files("seasynth.api.static.playground")

    @router.get("", response_class=HTMLResponse, include_in_schema=False)
    def index() -> HTMLResponse:
        return HTMLResponse(page.joinpath("index.html").read_text())

    @router.get("/static/{name}", include_in_schema=False)
    def static(name: str) -> Response:
        if name not in STATIC:
            raise NotFound(f"no playground file {name!r}")
        return Response(page.joinpath(name).read_bytes(), media_type=STATIC[name])

    @router.get("/config", response_model=PlaygroundConfig, response_model_by_alias=True)
    def config() -> PlaygroundConfig:
        return PlaygroundConfig(mode=mode, version=__version__, schema=DatasetSpec.model_json_schema(),
                                spec=start_spec, jerlov=jerlov_colours(), kinds=list(KINDS))

    # Thumbnails are committed PNGs drawn by the real renderer (examples/kind_thumbnails.py): the API has no GL.
    @router.get("/kinds/{kind}.png", response_class=Response, responses={
        200: {"content": {"image/png": {}}, "description": "Variants 0-2 of the kind on a sand seabed"},
        **error_responses(404)})
    def kind_thumbnail(kind: str) -> Response:
        """A small PNG of a procedural kind, for the asset picker."""
        if kind not in KINDS:
            raise NotFound(f"no procedural kind {kind!r}; the kinds are {', '.join(KINDS)}")
        return Response(page.joinpath("kinds", f"{kind}.png").read_bytes(), media_type="image/png",
                        headers={"Cache-Control": "public, max-age=86400"})

    @router.post("/validate", response_model=SpecChecked, responses=error_responses(400, 413, 422))
    def validate(body: SpecCheck) -> SpecChecked:
        """Validate a spec with the model POST /datasets uses; errors name each field by its path."""
        try:
            DatasetSpec.model_validate(body.spec)
        except ValidationError as err:
            return SpecChecked(valid=False, errors=field_errors(err))
        return SpecChecked(valid=True, errors=[], yaml=yaml.safe_dump(body.spec, sort_keys=False))

    def servable(request: Request, spec: DatasetSpec) -> DatasetSpec:
        if check is not None:
            check(request, spec)
        return spec

    def client_of(request: Request, given: str | None) -> str:
        return given or (request.client.host if request.client else "anonymous")

    busy = (400, 409, 413, 422, 502, 503)

    @router.post("/preview", response_model=PreviewPublic,
                 responses=error_responses(*busy, why={422: f"{SPEC_RULES}; and `frame` is below the spec's frames"}))
    async def preview(body: PreviewCreate, request: Request,
                      x_playground_client: Annotated[str | None, Header(max_length=64)] = None) -> dict:
        """Frame `frame` at the `draft` preset with the views asked for and its label boxes."""
        spec = servable(request, body.spec)
        if body.frame >= spec.frames:
            raise SpecError(f"frame: {body.frame} is past the spec's last frame ({spec.frames - 1})")
        views = sorted(set(body.views))
        return await gate.run(client_of(request, x_playground_client),
                              lambda: previewer_of(request).preview(spec, body.frame, views))

    @router.post("/strip", response_model=StripPublic, responses=error_responses(*busy, why={422: SPEC_RULES}))
    async def strip(body: StripCreate, request: Request,
                    x_playground_client: Annotated[str | None, Header(max_length=64)] = None) -> dict:
        """Thumbnails of frames first .. first+count-1 (those the spec has), to judge the randomisation."""
        spec = servable(request, body.spec)
        count = min(body.count, spec.frames - body.first)  # the strip stays within the dataset
        if count <= 0:
            return {"frames": []}
        return await gate.run(client_of(request, x_playground_client) + ":strip",
                              lambda: previewer_of(request).strip(spec, body.first, count))

    return router


class ServicePreviewer:
    """Previews rendered by a frames-queue worker of this version, answered through Redis like single frames."""

    def __init__(self, services: Any):
        self.services = services

    def _ask(self, kind: str, spec: DatasetSpec, args: list[Any]) -> dict:
        from seasynth.api.operations import publish, worker_error
        from seasynth.service.queues import TASK_PREVIEW, frame_queue
        from seasynth.service.records.store import wait_reply

        s = self.services
        timeout = s.settings.frame_timeout_s
        key = s.records.reply_key(uuid.uuid4().hex)
        publish(s, TASK_PREVIEW, [kind, spec.model_dump(mode="json"), args, key],
                frame_queue(s.settings.worker_version), expires=timeout)
        got = wait_reply(s.raw_redis, key, timeout)
        if got is None:
            raise Unavailable(f"no frame worker rendered the preview within {timeout:g} s")
        header, body = got
        if not header.get("ok"):
            raise worker_error(header, "the preview")
        try:
            return json.loads(body)
        except ValueError as err:
            raise RenderError(f"the frame worker's preview was not JSON ({err})") from None

    def preview(self, spec: DatasetSpec, frame: int, views: list[str]) -> dict:
        return self._ask("preview", spec, [frame, views])

    def strip(self, spec: DatasetSpec, first: int, count: int) -> dict:
        return self._ask("strip", spec, [first, count])
