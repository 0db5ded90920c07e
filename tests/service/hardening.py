"""What the API hardening tests share: an API on its own key prefix and worker version, served in this process on
real Redis and moto's S3 (fixtures settings, services, serve, api), and records made by hand."""

from __future__ import annotations

import dataclasses
import hashlib
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import pytest
from service_stack import Stack, free_port, tiny_spec, wait_for

from seasynth.service.records.store import Records
from seasynth.service.records.types import ShardCommit
from seasynth.service.shards import shard_count

VERSION = "0.0.0-hardening"  # no worker consumes these queues: what the API publishes stays where it was put
KEY = "k-hardening"


@contextmanager
def serving(app) -> Iterator[str]:
    """uvicorn serving `app` on a free port in a thread of this process."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 15, "uvicorn")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)


@pytest.fixture(scope="module")
def settings(infra: Stack):
    return infra.settings(key_prefix="hardening", worker_version=VERSION, max_spec_bytes=4096,
                          max_asset_bytes=20_000, api_keys=KEY, frame_timeout_s=20, retry_after_s=9)


@pytest.fixture(scope="module")
def services(settings):
    from seasynth.api.deps import open_services

    s = open_services(settings)
    yield s
    s.close()


@pytest.fixture
def serve(settings, services):
    """serve(**replaced services) -> base URL of an API on those services (real Redis and S3 unless replaced)."""
    from seasynth.api.main import create_app

    stack = []

    def start(**replace) -> str:
        ctx = serving(create_app(settings, dataclasses.replace(services, **replace)))
        stack.append(ctx)
        return ctx.__enter__()

    yield start
    for ctx in reversed(stack):
        ctx.__exit__(None, None, None)


@pytest.fixture
def api(serve) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=serve(), headers={"X-API-Key": KEY}, timeout=60) as c:
        yield c


def new_record(records: Records, *, frames: int, shard_size: int = 1, age_s: float = 0.0) -> str:
    import uuid

    dataset_id = uuid.uuid4().hex
    records.create(dataset_id, tiny_spec(frames=frames, shard_size=shard_size), seed=7, code_version=VERSION,
                   frames=frames, shard_size=shard_size, shards=shard_count(frames, shard_size),
                   now=time.time() - age_s)
    return dataset_id


def commit(records: Records, dataset_id: str, index: int, data: bytes, store=None) -> ShardCommit:
    key = f"datasets/{dataset_id}/shards/shard-{index:06d}.tar"
    if store is not None:
        store.put_bytes(key, data)
    c = ShardCommit(index=index, key=key, first_frame=index, frame_count=1, sha256=hashlib.sha256(data).hexdigest(),
                    bytes=len(data), code_version=VERSION, renderer="test")
    records.commit(dataset_id, c)
    return c
