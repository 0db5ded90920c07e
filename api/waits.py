"""The bound on frame requests waiting for a frame worker at once, checked before the request takes a thread."""

from __future__ import annotations

from starlette.routing import BaseRoute, Match

from seasynth.api.gate import ASGIApp, Receive, Scope, Send, answer


class FrameWaits:
    """Pure ASGI middleware: a request for `route` while `limit` of them are already waiting gets 503 with
    Retry-After at once.

    A frame request holds a thread of the pool sync routes run on (40 in all) for up to frame_timeout_s; without
    a bound, slow frame workers would leave no thread for any other sync route.
    """

    def __init__(self, app: ASGIApp, route: BaseRoute, limit: int, retry_after_s: int):
        self.app = app
        self.route = route
        self.limit = limit
        self.retry_after_s = retry_after_s
        self.waiting = 0  # only the event loop touches it, between awaits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self.route.matches(scope)[0] is not Match.FULL:
            await self.app(scope, receive, send)
            return
        if self.waiting >= self.limit:
            await answer(send, 503, f"{self.limit} frame requests are already waiting for a frame worker, the limit "
                         f"of this API process (SEASYNTH_MAX_FRAME_WAITS); retry after {self.retry_after_s} s",
                         {"Retry-After": str(self.retry_after_s)})
            return
        self.waiting += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.waiting -= 1
