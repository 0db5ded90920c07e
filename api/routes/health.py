"""Liveness and readiness; never behind an API key."""

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from seasynth.api.deps import ServicesDep
from seasynth.api.models import Health
from seasynth.service import __version__

router = APIRouter(tags=["health"])


# HEAD answers too (load balancers probe with it), each method under its own operation id in the OpenAPI document.
@router.get("/healthz", response_model=Health)
@router.head("/healthz", response_model=Health, operation_id="healthz_head")
async def healthz() -> Health:
    """The process is up: answered on the event loop, so busy threads of sync routes cannot delay it."""
    return Health(status="ok", version=__version__)


@router.get("/readyz", response_model=Health, responses={503: {"model": Health}})
@router.head("/readyz", response_model=Health, responses={503: {"model": Health}}, operation_id="readyz_head")
def readyz(services: ServicesDep):
    """Redis and the bucket are reachable."""
    checks, ok = {}, True
    try:
        services.records.ping()
        checks["redis"] = "ok"
    except Exception as err:  # any failure means not ready; the reason is reported, not hidden
        checks["redis"], ok = f"unreachable: {err}", False
    try:
        services.store.check()
        checks["storage"] = "ok"
    except Exception as err:
        checks["storage"], ok = f"unreachable: {err}", False
    body = Health(status="ok" if ok else "unavailable", version=__version__, checks=checks)
    return body if ok else JSONResponse(body.model_dump(), status_code=503)
