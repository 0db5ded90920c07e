"""Domain errors to HTTP answers, in one place. Every error body, 422 included, is {"detail": str, "errors": [str, ...]}
(api.models.ErrorPublic, the model the OpenAPI document declares for each error status)."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException
from starlette.routing import Match

from seasynth.service.errors import (
    AssetError,
    CalibrationError,
    Conflict,
    ExportError,
    LimitExceeded,
    NotFound,
    OutputError,
    ParameterError,
    RenderError,
    SeasynthError,
    SpecError,
    Unauthorized,
    Unavailable,
)
from seasynth.service.spec.dataset import field_path

log = logging.getLogger(__name__)

# Most specific first: the first class an error is an instance of decides its status.
STATUS: list[tuple[type[Exception], int]] = [
    (SpecError, 422),
    (AssetError, 422),
    (CalibrationError, 422),
    (ParameterError, 422),
    (LimitExceeded, 413),
    (NotFound, 404),
    (Conflict, 409),
    (Unauthorized, 401),
    (Unavailable, 503),
    (OutputError, 503),
    # In the API a RenderError is a frame worker's report that rendering failed: a fault behind this server,
    # and not one that waiting cures (so no 503 and no Retry-After).
    (RenderError, 502),
    # A stored shard the preview sheet cannot read (unreadable tar, a frame's file missing or undecodable): the data
    # behind this server is at fault, not the request.
    (ExportError, 502),
]


def error_body(message: str) -> dict:
    lines = [line for line in message.splitlines() if line.strip()] or [message]
    return {"detail": message, "errors": lines}


def status_of(err: Exception) -> int:
    for cls, code in STATUS:
        if isinstance(err, cls):
            return code
    return 500


def allowed_methods(request: Request) -> list[str]:
    """Every method some route of the request's path takes (a path's routes partly match any other method)."""
    scope = {**request.scope, "method": ""}
    methods: set[str] = set()
    for route in request.app.router.routes:
        if route.matches(scope)[0] is not Match.NONE:
            methods |= getattr(route, "methods", None) or set()
    return sorted(methods)


def install(app: FastAPI, retry_after_s: int) -> None:
    """Register the handlers that turn domain errors, bad requests and unreachable dependencies into HTTP."""

    async def domain(request: Request, err: SeasynthError) -> JSONResponse:
        code = status_of(err)
        if code >= 500:
            log.error("%s %s: %s", request.method, request.url.path, err)
        headers = {}
        if code == 503:
            headers["Retry-After"] = str(retry_after_s)
        if code == 401:
            headers["WWW-Authenticate"] = 'Bearer realm="seasynth"'
        return JSONResponse(error_body(str(err)), status_code=code, headers=headers)

    async def invalid(request: Request, err: RequestValidationError) -> JSONResponse:
        broken = [e for e in err.errors() if e.get("type") == "json_invalid"]
        if broken:
            e = broken[0]
            at = e["loc"][-1] if len(e.get("loc", ())) > 1 else 0
            reason = (e.get("ctx") or {}).get("error", "invalid JSON")
            return JSONResponse(error_body(f"malformed JSON in the request body at character {at}: {reason}"),
                                status_code=400)
        lines = []
        for e in err.errors():
            loc = list(e.get("loc", ()))
            if loc and loc[0] == "body":  # the body is the spec: name fields as spec files do
                loc = loc[1:]
            where = field_path(loc, err.body) or "(body)"
            lines.append(f"{where}: {str(e.get('msg', 'invalid')).removeprefix('Value error, ')}")
        return JSONResponse({"detail": "invalid request\n" + "\n".join(lines), "errors": lines}, status_code=422)

    async def redis_down(request: Request, err: Exception) -> JSONResponse:
        log.error("%s %s: Redis: %s", request.method, request.url.path, err)
        return JSONResponse(
            error_body(f"status store unavailable: {err}"), status_code=503, headers={"Retry-After": str(retry_after_s)}
        )

    async def http(request: Request, err: HTTPException) -> JSONResponse:
        # Starlette's own answers (unknown path, wrong method, unparsable form) in the same body shape.
        headers = dict(err.headers or {})
        if err.status_code == 405:  # Starlette names only the first route of the path; a path has several
            headers["Allow"] = ", ".join(allowed_methods(request))
        return JSONResponse(error_body(str(err.detail)), status_code=err.status_code, headers=headers)

    import redis

    app.add_exception_handler(HTTPException, http)
    app.add_exception_handler(SeasynthError, domain)
    app.add_exception_handler(RequestValidationError, invalid)
    app.add_exception_handler(redis.RedisError, redis_down)
