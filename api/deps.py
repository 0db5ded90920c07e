"""Dependencies: the per-app Services (Redis, storage, task producer), dataset ids and frame indices from paths.

API keys are checked before any route runs, by api/gate.py."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Path, Query, Request

from seasynth.service.errors import NotFound
from seasynth.service.records.store import Records, raw_client
from seasynth.service.settings import Settings
from seasynth.service.shards import DATASET_ID
from seasynth.service.storage import ObjectStore


@dataclass
class Services:
    """What the routes use; opened in the app's lifespan, never at import."""

    settings: Settings
    records: Records
    raw_redis: Any  # decode_responses=False: single-frame answers are bytes
    store: ObjectStore
    producer: Any  # a Celery app used only to publish tasks by name

    def close(self) -> None:
        self.records.close()
        self.raw_redis.close()


def open_services(settings: Settings) -> Services:
    from celery import Celery

    from seasynth.service.queues import broker_options
    from seasynth.service.storage import open_store

    producer = Celery("seasynth-api", broker=settings.redis_url, set_as_current=False)
    producer.conf.update(
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,
        broker_transport_options=broker_options(settings.visibility_timeout_s),
        broker_connection_retry_on_startup=True,
    )
    return Services(
        settings=settings,
        records=Records.from_url(settings.redis_url, settings.key_prefix),
        # BLPOP waits up to frame_timeout_s for a frame: the socket must outwait it (redis-py's default is 5 s).
        raw_redis=raw_client(settings.redis_url, socket_timeout=settings.frame_timeout_s + 10),
        store=open_store(settings),
        producer=producer,
    )


# The dependencies below do no I/O, so they are `async def`: FastAPI runs a plain `def` dependency on the thread
# pool, two thread hand-offs per status read that cost more CPU than the read itself (bench/load.py).


async def get_services(request: Request) -> Services:
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]


async def dataset_id(id: Annotated[str, Path(description="Dataset id (32 lowercase hex digits)")]) -> str:
    """A syntactically valid dataset id; any other string names no dataset (404, like an unknown id)."""
    if not DATASET_ID.fullmatch(id):
        raise NotFound(f"no dataset {id[:80]!r}")
    return id


DatasetId = Annotated[str, Depends(dataset_id)]

# Decimal digits only: " 1", "+1", "1.0" and "1_0" name no frame (int() and pydantic would read them as 1 or 10).
FRAME_INDEX = re.compile(r"^[0-9]{1,19}$")


async def frame_index(index: Annotated[str, Path(description="Frame index: decimal digits, from 0")]) -> int:
    """A frame index written plainly; any other string names no frame (404)."""
    if not FRAME_INDEX.fullmatch(index):
        raise NotFound(f"no frame {index[:40]!r} (a frame index is written in decimal digits)")
    return int(index)


FrameIndex = Annotated[int, Depends(frame_index)]


# A list's page: offset and limit in the query, and the link to the next page while there is one.
PageOffset = Annotated[int, Query(ge=0, le=10**9)]
PageLimit = Annotated[int, Query(ge=1, le=100)]


def next_page(path: str, offset: int, limit: int, total: int) -> str | None:
    return f"{path}?offset={offset + limit}&limit={limit}" if offset + limit < total else None
