"""Dataset routes: create, list, status, manifest, single frames, preview sheet, cancel, delete and reconcile.

Every status a route can answer is declared, each error with the one body model (seasynth.api.models.ErrorPublic)."""

from typing import Annotated, Literal

from fastapi import APIRouter, Body, Query, Response, status

from seasynth.api import operations
from seasynth.api.deps import DatasetId, FrameIndex, PageLimit, PageOffset, ServicesDep, next_page
from seasynth.api.models import (
    SPEC_EXAMPLE,
    SPEC_RULES,
    DatasetCreated,
    DatasetList,
    DatasetPublic,
    ManifestPublic,
    error_responses,
)
from seasynth.service.previews import MAX_SHEET_FRAMES, SHEET_FRAMES, dataset_preview
from seasynth.service.shards import media_type
from seasynth.service.sheet import TILE_WIDTH
from seasynth.service.spec.dataset import DatasetSpec

# Any route: no key (401), a bad parameter (422), Redis down (503).
router = APIRouter(prefix="/datasets", tags=["datasets"], responses=error_responses(401, 422, 503))

@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=DatasetCreated,
             responses=error_responses(400, 413, 422, why={422: SPEC_RULES}))
def create_dataset(spec: Annotated[DatasetSpec, Body(openapi_examples={"small": {"value": SPEC_EXAMPLE}})],
                   services: ServicesDep, response: Response) -> DatasetCreated:
    """Accept a dataset spec (the spec-file schema as JSON) and queue its shards."""
    created = operations.create_dataset(services, spec)
    response.headers["Location"] = created.links.self
    return created


@router.get("", response_model=DatasetList)
def list_datasets(services: ServicesDep, offset: PageOffset = 0, limit: PageLimit = 20) -> DatasetList:
    """Datasets, newest first."""
    items, total = operations.list_datasets(services, offset, limit)
    return DatasetList(items=items, total=total, offset=offset, limit=limit,
                       next=next_page("/datasets", offset, limit, total))


@router.get("/{id}", response_model=DatasetPublic, responses=error_responses(404))
def get_dataset(id: DatasetId, services: ServicesDep) -> DatasetPublic:
    """State, progress (frames_done counts committed shards only), frames/s, ETA and shard errors."""
    return operations.dataset_status(services, id)


@router.get("/{id}/manifest", response_model=ManifestPublic, responses=error_responses(404))
def get_manifest(
    id: DatasetId,
    services: ServicesDep,
    start: Annotated[int, Query(ge=0, le=10**9, description="First shard index of the page")] = 0,
    limit: Annotated[
        int, Query(ge=1, le=operations.MANIFEST_PAGE_MAX, description="Shard indices per page")
    ] = operations.MANIFEST_PAGE,
) -> dict:
    """Committed shards so far (key, frames, sha256, bytes, presigned url), with spec, seed and code version,
    one page of shard indices at a time: follow `next` until it is null."""
    return operations.manifest(services, id, start, limit)


@router.get(
    "/{id}/frames/{index}",
    response_class=Response,
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}, "text/plain": {}, "application/json": {},
                                 "application/octet-stream": {}}},
               **error_responses(404, 502)},
)
def get_frame(
    id: DatasetId,
    index: FrameIndex,
    services: ServicesDep,
    part: Annotated[
        Literal["image", "label", "calib", "meta", "depth", "instance", "semantic", "clean", "range", "fls", "fls_fan",
                "fls_label", "sss", "sss_label", "nav"],
        Query(description="Which of the frame's files: the image by default (PNG, or JPEG where the spec's "
                          "outputs.image_format is jpeg)"),
    ] = "image",
) -> Response:
    """Re-render frame `index` from (spec, seed, index) on a worker: byte-identical to the file in its shard."""
    name, body = operations.frame(services, id, index, part)
    return Response(body, media_type=media_type(name),
                    headers={"Content-Disposition": f'inline; filename="{name.replace("/", "_")}"'})


@router.get(
    "/{id}/preview.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}},
                     "description": "The contact sheet: the first frames with their boxes (depth and instances where "
                                    "the spec has them) over a label summary of the shards drawn from"},
               **error_responses(404, 502)},
)
def get_preview(
    id: DatasetId,
    services: ServicesDep,
    frames: Annotated[int, Query(ge=1, le=MAX_SHEET_FRAMES, description="Frames on the sheet")] = SHEET_FRAMES,
    tile_width: Annotated[int, Query(ge=1, le=4096, description="Widest image panel, px; wider frames are "
                                     "scaled down")] = TILE_WIDTH,
) -> Response:
    """A contact sheet of the dataset's first committed shards, drawn once and then served from the bucket."""
    key, png = dataset_preview(services.store, services.records, id, frames, tile_width)
    return Response(png, media_type="image/png",
                    headers={"Content-Disposition": f'inline; filename="{id}-preview.png"',
                             "ETag": f'"{key.rsplit("/", 1)[-1].removesuffix(".png")}"'})


@router.post("/{id}/cancel", response_model=DatasetPublic, responses=error_responses(404, 409))
def cancel_dataset(id: DatasetId, services: ServicesDep) -> DatasetPublic:
    """Cancel at once: pending shards are not rendered, committed ones are kept. Cancelling a cancelled dataset
    again is harmless; a finished one is 409."""
    return operations.cancel_dataset(services, id)


@router.delete("/{id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response,
               responses=error_responses(404))
def delete_dataset(id: DatasetId, services: ServicesDep) -> Response:
    """Delete the dataset: cancel it if live, delete its objects, and drop it from the API (every route then
    answers 404). A delete the bucket fails is 503 and may be repeated."""
    operations.delete_dataset(services, id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post("/{id}/reconcile", response_model=DatasetPublic, status_code=status.HTTP_202_ACCEPTED,
             responses=error_responses(404))
def reconcile(
    id: DatasetId,
    services: ServicesDep,
    requeue: Annotated[bool, Query(description="Publish every pending shard again (after losing the broker)")] = False,
) -> DatasetPublic:
    """Ask a worker to adopt commit markers Redis missed and finalise a complete dataset."""
    return operations.reconcile_dataset(services, id, requeue)
