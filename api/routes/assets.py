"""User assets: meshes and textures uploaded once, referenced from specs by their sha256 id."""

from pathlib import PurePosixPath

from fastapi import APIRouter, Response, UploadFile, status

from seasynth.api import asset_store
from seasynth.api.deps import ServicesDep
from seasynth.api.models import AssetPublic, error_responses

router = APIRouter(prefix="/assets", tags=["assets"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=AssetPublic,
    responses={200: {"model": AssetPublic, "description": "These bytes were already uploaded in this format"},
               **error_responses(400, 401, 409, 413, 422, 503)},
)
def upload_asset(file: UploadFile, services: ServicesDep, response: Response) -> AssetPublic:
    """Upload a mesh (.glb, .obj, .ply, .stl) or texture (.png, .jpg) as multipart field `file`.

    A mesh must load with triangles and finite vertices, an image must decode. The first upload of some bytes
    fixes their format: 201 then, 200 for the same bytes again in the same format, 409 in another."""
    name = PurePosixPath((file.filename or "").replace("\\", "/")).name
    info, created = asset_store.store_asset(services, name, file.file)
    if not created:
        response.status_code = status.HTTP_200_OK
    return AssetPublic(asset_id=info["sha256"], filename=info["filename"], bytes=info["bytes"],
                       format=info["format"], kind=info["kind"])
