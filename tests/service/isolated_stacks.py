"""Isolated service stacks for the worker tests: a Redis database of their own (so the session's workers take none
of their messages), dataset records made directly, an API served in the test's process, and the queue read back."""

from __future__ import annotations

import base64
import contextlib
import json
import threading
import time
import uuid
from collections.abc import Iterator

import httpx
from service_stack import Stack, wait_for

from seasynth.service import __version__
from seasynth.service.shards import shard_count


def queued_tasks(raw, queue: str) -> list[tuple[str, list]]:
    """(task name, args) of every message waiting in `queue` or delivered and unacknowledged, oldest first."""
    out = []
    payloads = [m for m in raw.lrange(queue, 0, -1)][::-1]
    payloads += [json.loads(v)[0] for v in raw.hvals("unacked")]
    for p in payloads:
        msg = json.loads(p) if isinstance(p, (bytes, str)) else p
        body = json.loads(base64.b64decode(msg["body"]))
        out.append((msg["headers"]["task"], body[0]))
    return out


@contextlib.contextmanager
def isolated(stack: Stack, db: int, **settings) -> Iterator[tuple[dict[str, str], object]]:
    """(environment, services) on Redis database `db`, emptied before and after."""
    import redis

    from seasynth.api.deps import open_services

    url = stack.settings().redis_url.rsplit("/", 1)[0] + f"/{db}"
    raw = redis.Redis.from_url(url)
    raw.flushdb()
    services = open_services(stack.settings(redis_url=url, **settings))
    env = {"SEASYNTH_REDIS_URL": url, **{f"SEASYNTH_{k.upper()}": str(v) for k, v in settings.items()}}
    try:
        yield env, services
    finally:
        raw.flushdb()
        raw.close()
        services.close()


def record_only(services, spec: dict, *, age_s: float = 0, version: str = __version__) -> str:
    from seasynth.service.spec.dataset import parse_spec

    s = parse_spec(spec)
    dataset_id = uuid.uuid4().hex
    services.records.create(dataset_id, s.model_dump(mode="json"), seed=s.seed, code_version=version,
                            frames=s.frames, shard_size=s.shard_size, shards=shard_count(s.frames, s.shard_size),
                            now=time.time() - age_s)
    return dataset_id


@contextlib.contextmanager
def api_on(services) -> Iterator[httpx.Client]:
    """An API on `services`, served in this process."""
    import uvicorn
    from service_stack import free_port

    from seasynth.api.main import create_app

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(services.settings, services), host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 15, "uvicorn")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as client:
            yield client
    finally:
        server.should_exit = True
        thread.join(15)
