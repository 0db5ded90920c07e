"""Bounded CPU work in an API process: at most N jobs at once, in threads, one at a time per client with the newest
request winning (playground renders, water calibrations)."""

from __future__ import annotations

import asyncio
import time
import uuid
from collections.abc import Callable
from typing import TypeVar

from fastapi.concurrency import run_in_threadpool

from seasynth.service.errors import Conflict, Unavailable

T = TypeVar("T")


class RenderGate:
    """At most `slots` jobs at once, and one per client: a client's request waits for its running one (a render in
    a thread cannot be stopped), and of its waiting requests only the newest runs (older ones get 409). A request
    that finds no slot within `wait_s` (its client's running job included) gets 503 with the `busy` message."""

    def __init__(self, slots: int, wait_s: float = 2.0, busy: str = "the playground's renderer is busy; try again "
                 "shortly"):
        self._slots = asyncio.Semaphore(slots)
        self._wait_s = wait_s
        self._busy = busy
        self._latest: dict[str, str] = {}
        self._clients: dict[str, tuple[asyncio.Lock, int]] = {}  # client -> (its lock, requests holding or waiting)

    async def run(self, client: str, fn: Callable[[], T]) -> T:
        token = uuid.uuid4().hex
        self._latest[client] = token
        lock, users = self._clients.get(client, (None, 0))
        lock = lock or asyncio.Lock()
        self._clients[client] = (lock, users + 1)
        try:
            deadline = time.monotonic() + self._wait_s
            try:
                await asyncio.wait_for(lock.acquire(), self._wait_s)
            except TimeoutError:
                raise Unavailable(self._busy) from None
            try:
                try:
                    await asyncio.wait_for(self._slots.acquire(), max(0.0, deadline - time.monotonic()))
                except TimeoutError:
                    raise Unavailable(self._busy) from None
                try:
                    if self._latest.get(client) != token:  # checked with both held: a newer one came meanwhile
                        raise Conflict("superseded by a newer request from the same client")
                    return await run_in_threadpool(fn)
                finally:
                    self._slots.release()
            finally:
                lock.release()
        finally:  # also when a wait timed out or the request was cancelled while it waited
            if self._latest.get(client) == token:
                del self._latest[client]
            lock, users = self._clients[client]
            if users == 1:
                del self._clients[client]
            else:
                self._clients[client] = (lock, users - 1)
