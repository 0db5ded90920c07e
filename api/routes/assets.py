"""User assets: meshes and textures uploaded once, referenced from specs by their sha256 id."""

from pathlib import PurePosixPath
from typing import Annotated

from fastapi import APIRouter, File, Response, UploadFile, status

from seasynth.api import asset_store
from seasynth.api.deps import ServicesDep
from seasynth.api.models import UPLOAD_RULES, AssetPublic, error_responses, file_names
from seasynth.api.uploads import FORMATS

router = APIRouter(prefix="/assets", tags=["assets"])


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
