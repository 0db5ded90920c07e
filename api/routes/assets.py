"""User assets: meshes and textures uploaded once, referenced from specs by their sha256 id."""

from pathlib import PurePosixPath

from fastapi import APIRouter, Response, UploadFile, status

from api import operations
from api.deps import ServicesDep
from api.models import AssetPublic

router = APIRouter(prefix="/assets", tags=["assets"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=AssetPublic,
    responses={200: {"model": AssetPublic, "description": "These bytes were already uploaded in this format"},
               409: {"description": "These bytes were already uploaded in another format (named)"},
               413: {"description": "Over SEASYNTH_MAX_ASSET_BYTES"},
               422: {"description": "Not a mesh or image that loads (named)"}},
)
def upload_asset(file: UploadFile, services: ServicesDep, response: Response) -> AssetPublic:
    """Upload a mesh (.glb, .obj, .ply, .stl) or texture (.png, .jpg) as multipart field `file`.

    A mesh must load with triangles and finite vertices, an image must decode. The first upload of some bytes
    fixes their format: 201 then, 200 for the same bytes again in the same format, 409 in another."""
    name = PurePosixPath((file.filename or "").replace("\\", "/")).name
    info, created = operations.store_asset(services, name, file.file)
    if not created:
        response.status_code = status.HTTP_200_OK
    return AssetPublic(asset_id=info["sha256"], filename=info["filename"], bytes=info["bytes"],
                       format=info["format"], kind=info["kind"])
