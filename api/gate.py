"""The ASGI gate in front of every route: the API key, then the request body's size, checked before any route
reads the body (FastAPI parses and spools a body before it runs a route's dependencies)."""

from __future__ import annotations

import hmac
import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any, get_args

from seasynth.service.settings import Settings
from seasynth.service.spec.scene import ProceduralTarget

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

# Liveness and readiness probes carry no key, nor does the playground's static page: it holds no data, and asks
# the user for a key that its calls then send. Its kinds' thumbnails are <img> sources, which send no key.
PUBLIC_PATHS = frozenset({"/healthz", "/readyz", "/playground", "/playground/static/app.js",
                          "/playground/static/classes.js", "/playground/static/style.css"}
                         | {f"/playground/kinds/{kind}.png" for kind in get_args(ProceduralTarget)})
METRICS_PATH = "/metrics"  # public only with SEASYNTH_METRICS_PUBLIC=true
UPLOAD_PATH = "/assets"
CALIBRATE_PATH = "/calibrate"  # a photo and its range map: the upload limit holds for the whole body
# A multipart body holds the file plus its part headers and boundaries: room for those over the file limit.
UPLOAD_FRAMING_BYTES = 64 * 1024


class BodyTooLarge(Exception):
    """Raised from `receive` once a streamed body passes its limit; the gate answers 413 itself."""


def api_key_ok(headers: dict[str, str], keys: frozenset[str]) -> bool:
    """True when X-API-Key or Authorization: Bearer holds one of `keys`; an empty header counts as absent.

    Every given value is compared with every key in constant time, with no early exit: how long the check takes
    tells nothing about which key matched, or how much of one."""
    given = [headers.get("x-api-key", "").strip()]
    auth = headers.get("authorization", "")
    if auth[:7].lower() == "bearer ":
        given.append(auth[7:].strip())
    matched = False
    for g in given:
        for k in keys:
            matched |= hmac.compare_digest(g.encode(), k.encode()) & bool(g)
    return matched


def body_limit(settings: Settings, method: str, path: str) -> tuple[int, str]:
    """The most bytes a request's body may have, and how to name that limit in a 413."""
    if method == "POST" and path.rstrip("/") in (UPLOAD_PATH, CALIBRATE_PATH):
        named = (f"{settings.max_asset_bytes} bytes of file (SEASYNTH_MAX_ASSET_BYTES) plus "
                 f"{UPLOAD_FRAMING_BYTES} bytes of multipart framing")
        return settings.max_asset_bytes + UPLOAD_FRAMING_BYTES, named
    return settings.max_spec_bytes, f"{settings.max_spec_bytes} bytes (SEASYNTH_MAX_SPEC_BYTES)"


async def answer(send: Send, status: int, message: str, headers: dict[str, str] | None = None) -> None:
    """An error in the API's usual body: {"detail": str, "errors": [str]}."""
    body = json.dumps({"detail": message, "errors": [message]}).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class Gate:
    """Pure ASGI middleware: 401 without a valid key (SEASYNTH_API_KEYS set) and 413 for a body over its limit,
    by Content-Length before anything is read, or while a chunked body streams in."""

    def __init__(self, app: ASGIApp, settings: Settings):
        self.app = app
        self.settings = settings
        self.keys = settings.api_key_set
        self.public = PUBLIC_PATHS | ({METRICS_PATH} if settings.metrics_public else set())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        root = scope.get("root_path", "")
        if root and path.startswith(root):
            path = path[len(root):] or "/"
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if self.keys and path not in self.public and not api_key_ok(headers, self.keys):
            await answer(send, 401, "a valid API key is required (X-API-Key header or Authorization: Bearer)",
                         {"WWW-Authenticate": 'Bearer realm="seasynth"'})
            return
        limit, named = body_limit(self.settings, scope["method"], path)
        declared = headers.get("content-length")
        if declared is not None:
            if not declared.isdigit():
                await answer(send, 400, f"invalid Content-Length header {declared[:40]!r}")
                return
            if int(declared) > limit:
                await answer(send, 413, f"request body of {int(declared)} bytes is over the limit of {named}")
                return

        received = 0
        over = started = False

        async def counted() -> Message:
            nonlocal received, over
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    over = True
                    raise BodyTooLarge(named)
            return message

        async def guarded(message: Message) -> None:
            nonlocal started
            if over:  # the route's own answer to the aborted read is replaced by the 413 below
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted, guarded)
        except BodyTooLarge:
            pass
        except Exception:
            if not over:
                raise
        if over and not started:
            await answer(send, 413, f"request body is over the limit of {named} (stopped after {received} bytes)")
