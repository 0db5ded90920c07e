"""Bounded CPU work in an API process: at most N jobs at once, in threads, the newest per client winning (playground
renders, water calibrations)."""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import Callable
from typing import TypeVar

from fastapi.concurrency import run_in_threadpool

from service.errors import Conflict, Unavailable

T = TypeVar("T")


class RenderGate:
    """At most `slots` jobs at once; per client, only the newest request runs (older waiting ones get 409), and a
    request that finds no slot within `wait_s` gets 503 with the `busy` message."""

    def __init__(self, slots: int, wait_s: float = 2.0, busy: str = "the playground's renderer is busy; try again "
                 "shortly"):
        self._slots = asyncio.Semaphore(slots)
        self._wait_s = wait_s
        self._busy = busy
        self._latest: dict[str, str] = {}

    async def run(self, client: str, fn: Callable[[], T]) -> T:
        token = uuid.uuid4().hex
        self._latest[client] = token
        try:
            try:
                await asyncio.wait_for(self._slots.acquire(), self._wait_s)
            except TimeoutError:
                raise Unavailable(self._busy) from None
            try:
                if self._latest.get(client) != token:
                    raise Conflict("superseded by a newer request from the same client")
                return await run_in_threadpool(fn)
            finally:
                self._slots.release()
        finally:  # also when the wait timed out or the request was cancelled while it waited
            if self._latest.get(client) == token:
                del self._latest[client]
