"""Real components for the service tests, started here on free ports: redis-server, moto's S3 server, the API
(`seasynth serve`) and two render workers (`seasynth worker`). Logs go to the session's temp folder and are
printed when a component fails to start."""

from __future__ import annotations

import os
from collections.abc import Iterator

import httpx
import pytest
from service_stack import BUCKET, Stack, free_port, need, wait_for


@pytest.fixture(scope="session")
def infra(tmp_path_factory) -> Iterator[Stack]:
    """redis-server and moto_server on free ports, and the environment every component gets."""
    tmp = tmp_path_factory.mktemp("stack")
    redis_port, s3_port = free_port(), free_port()
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith(("SEASYNTH_", "AWS_"))},
        "SEASYNTH_REDIS_URL": f"redis://127.0.0.1:{redis_port}/0",
        "SEASYNTH_S3_ENDPOINT_URL": f"http://127.0.0.1:{s3_port}",
        "SEASYNTH_S3_BUCKET": BUCKET,
        "SEASYNTH_S3_CREATE_BUCKET": "true",
        # A frame or preview of a water no process met yet waits on its column solves first: the playground's
        # default spec's first preview took 118 s on the 2-core CPU from an empty cache folder, more beside the
        # compose test's builds (CI), so 300.
        "SEASYNTH_FRAME_TIMEOUT_S": "300",
        "SEASYNTH_WORKER_SOFT_SHUTDOWN_S": "2",
        "SEASYNTH_TASK_TIME_LIMIT_S": "300",  # shard_size 1000 of tiny frames fits its budget
        "SEASYNTH_MAX_FRAMES": "500000",  # below the spec's own cap (1,000,000), so both refusals can be seen
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "PYTHONUNBUFFERED": "1",
    }
    stack = Stack(tmp, env)
    redis = stack.start("redis", [need("redis-server"), "--port", str(redis_port), "--bind", "127.0.0.1",
                                  "--save", "", "--appendonly", "no", "--maxmemory-policy", "noeviction",
                                  "--dir", str(tmp)])
    s3 = stack.start("s3", [need("moto_server"), "-H", "127.0.0.1", "-p", str(s3_port)])
    import redis as redis_py

    try:
        wait_for(lambda: redis_py.Redis(port=redis_port).ping(), 15, "redis-server")
        wait_for(lambda: httpx.get(env["SEASYNTH_S3_ENDPOINT_URL"], timeout=2).status_code < 500, 30, "moto_server")
    except TimeoutError as err:
        raise RuntimeError(f"{err}\nredis:\n{redis.tail()}\ns3:\n{s3.tail()}") from None
    os.environ.update({k: env[k] for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION")})
    yield stack
    for p in reversed(stack.procs):
        p.stop()


@pytest.fixture(scope="session")
def stack(infra: Stack) -> Stack:
    """The whole service: API plus two single-process workers."""
    infra.start_worker(1)
    infra.start_worker(1)
    infra.api_proc, infra.api_url = infra.start_api()
    return infra


@pytest.fixture(scope="session")
def services(infra: Stack):
    """In-process access to the same Redis records and bucket, for assertions."""
    from seasynth.api.deps import open_services

    s = open_services(infra.settings())
    yield s
    s.close()


@pytest.fixture
def client(stack: Stack) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=stack.api_url, timeout=60) as c:
        yield c


