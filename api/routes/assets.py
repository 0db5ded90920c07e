"""User assets: meshes and textures uploaded once, referenced from specs by their sha256 id."""

from pathlib import PurePosixPath

from fastapi import APIRouter, UploadFile, status

from api import operations
from api.deps import ServicesDep
from api.models import AssetPublic

router = APIRouter(prefix="/assets", tags=["assets"])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=AssetPublic)
def upload_asset(file: UploadFile, services: ServicesDep) -> AssetPublic:
    """Upload a mesh (.glb, .obj, .ply, .stl) or texture (.png, .jpg) as multipart field `file`."""
    name = PurePosixPath((file.filename or "").replace("\\", "/")).name
    asset_id, size = operations.store_asset(services, name, file.file)
    return AssetPublic(asset_id=asset_id, filename=name, bytes=size)
