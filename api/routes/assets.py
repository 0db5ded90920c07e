"""User assets: meshes and textures uploaded once, referenced from specs by their sha256 id; listed, and each mesh
with a picture (the playground's asset picker shows them)."""

import hashlib
from pathlib import PurePosixPath
from typing import Annotated

from fastapi import APIRouter, File, Header, Path, Response, UploadFile, status

from seasynth.api import asset_store
from seasynth.api.deps import PageLimit, PageOffset, ServicesDep, next_page
from seasynth.api.models import UPLOAD_RULES, AssetList, AssetListed, AssetPublic, error_responses, file_names
from seasynth.api.uploads import FORMATS, MESH

router = APIRouter(prefix="/assets", tags=["assets"])
# A picture is drawn from content-addressed bytes: the same id keeps its picture (until a release draws them anew).
THUMBNAIL_MAX_AGE_S = 86400


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=AssetPublic,
    responses={200: {"model": AssetPublic, "description": "These bytes were already uploaded in this format"},
               **error_responses(400, 401, 409, 413, 422, 503, why={422: f"{UPLOAD_RULES}, the format its name's "
                                 "suffix says: a mesh that loads with triangles and finite vertices (a .zip: a safe "
                                 "archive of one glTF or OBJ and its files), or an image that decodes whole; "
                                 "textures within the pixel budget"})},
    openapi_extra=file_names(file=(tuple(FORMATS), "mesh.ply")),
)
def upload_asset(file: Annotated[UploadFile, File(description="The mesh or texture; its file name's suffix sets "
                                                  "the format")],
                 services: ServicesDep, response: Response) -> AssetPublic:
    """Upload a mesh (.glb, .obj, .ply, .stl, or a .zip of a textured glTF or OBJ with its files) or texture
    (.png, .jpg) as multipart field `file`.

    A mesh must load with triangles and finite vertices, an image must decode. A .zip holds exactly one .gltf, .glb
    or .obj (at its top level or in a folder there) with the buffers, MTL and PNG or JPEG images it names; members
    with unsafe names (`..`, absolute), links, duplicates, encryption, too many members or bytes, or bomb-like
    compression are refused naming the member, as is an image over the pixel budget. The first upload of some bytes
    fixes their format: 201 then, 200 for the same bytes again in the same format, 409 in another."""
    name = PurePosixPath((file.filename or "").replace("\\", "/")).name
    info, created = asset_store.store_asset(services, name, file.file)
    if not created:
        response.status_code = status.HTTP_200_OK
    return AssetPublic(asset_id=info["sha256"], filename=info["filename"], bytes=info["bytes"],
                       format=info["format"], kind=info["kind"])


@router.get("", response_model=AssetList, responses=error_responses(401, 422, 503))
def list_assets(services: ServicesDep, offset: PageOffset = 0, limit: PageLimit = 50) -> AssetList:
    """Uploaded assets, newest first: id, first file name, format, kind, bytes, upload time, and a mesh's picture."""
    items, total = asset_store.list_assets(services, offset, limit)
    nxt = next_page("/assets", offset, limit, total)
    return AssetList(items=[AssetListed(
        asset_id=a["sha256"], filename=a["filename"], bytes=a["bytes"], format=a["format"], kind=a["kind"],
        uploaded_at=a["uploaded_at"], thumbnail=f"/assets/{a['sha256']}/thumbnail.png" if a["kind"] == MESH else None,
    ) for a in items], total=total, offset=offset, limit=limit, next=nxt)


@router.get(
    "/{asset_id}/thumbnail.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "The mesh flat-shaded in a three-quarter view, "
                     "128x96, transparent around it"},
               304: {"description": "The picture the client holds (If-None-Match) is this one"},
               **error_responses(401, 404, 422, 503, why={
                   404: "No such asset, an image (pictures are drawn for meshes), or a mesh no picture could be "
                        "drawn of (the message says why; the mesh itself is valid)"})},
)
def get_thumbnail(
    asset_id: Annotated[str, Path(description="The asset's id (64 lowercase hex digits)")],
    services: ServicesDep,
    if_none_match: Annotated[str | None, Header(max_length=200)] = None,
) -> Response:
    """A picture of uploaded mesh `asset_id` for the playground's asset picker, drawn without OpenGL at upload
    (or at the first request, for a mesh uploaded before pictures were drawn), then kept."""
    png = asset_store.thumbnail(services, asset_id)
    etag = f'"{hashlib.sha256(png).hexdigest()[:32]}"'
    headers = {"ETag": etag, "Cache-Control": f"private, max-age={THUMBNAIL_MAX_AGE_S}"}
    if if_none_match is not None and etag in [t.strip() for t in if_none_match.split(",")]:
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers=headers)
    return Response(png, media_type="image/png", headers=headers)
