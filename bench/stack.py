"""The service on this machine, for benches: redis-server, an S3 server (moto's) or a local folder, the API
(`seasynth serve`) and render workers (`seasynth worker`), each a process on free loopback ports, logs in a folder.

    with local_stack(folder, concurrency=16, worker_env={"SEASYNTH_GPUS": "2"}) as stack:
        httpx.post(f"{stack.api}/datasets", json=spec, headers=stack.headers)

What a fresh machine lacks (redis-server, moto_server) is named with how to install it before anything starts.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

BUCKET = "seasynth-bench"
READY = "render session ready"  # a pool process's log line once its renderer is open (worker/queue/tasks.py)


class MissingComponent(RuntimeError):
    """A program the stack needs is not installed; the message says how to install it."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def find_program(name: str, install: str) -> str:
    """`name` on PATH or beside this Python (a virtualenv's scripts); MissingComponent saying `install` if absent."""
    path = shutil.which(name) or str(Path(sys.executable).parent / name)
    if not os.access(path, os.X_OK):
        raise MissingComponent(f"{name} is needed to run the service here and was not found on PATH or in "
                               f"{Path(sys.executable).parent}: {install}")
    return path


def wait(pred: Callable[[], Any], timeout: float, what: str, procs: list[subprocess.Popen] = ()) -> None:
    """Until pred() is true (exceptions count as not yet); RuntimeError as soon as one of `procs` exits."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(p.poll() is not None for p in procs):
            raise RuntimeError(f"a component exited while waiting for {what}")
        try:
            if pred():
                return
        except Exception:  # still starting
            pass
        time.sleep(0.1)
    raise TimeoutError(f"{what} did not come up in {timeout} s")


@dataclass
class LocalStack:
    folder: Path
    env: dict[str, str]  # what every component got: SEASYNTH_* settings and S3 credentials
    api: str = ""
    api_key: str | None = None
    worker_metrics: str | None = None
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)

    @property
    def headers(self) -> dict[str, str]:
        return {"X-API-Key": self.api_key} if self.api_key else {}

    def log(self, name: str, lines: int = 40) -> str:
        try:
            return "\n".join((self.folder / f"{name}.log").read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def settings(self):
        """The components' Settings, for reading the records and the bucket from this process."""
        from seasynth.service.settings import Settings

        return Settings(**{k[len("SEASYNTH_"):].lower(): v for k, v in self.env.items() if k.startswith("SEASYNTH_")})

    def store(self):
        """The stack's object store, opened in this process with the components' credentials (boto3 takes them
        from its own chain, the environment, when the client is made)."""
        from unittest import mock

        from seasynth.service.storage import open_store

        with mock.patch.dict(os.environ, {k: v for k, v in self.env.items() if k.startswith("AWS_")}):
            return open_store(self.settings())


@contextmanager
def local_stack(folder: Path, *, concurrency: int = 1, queues: str = "shards", api_key: str | None = None,
                worker_env: dict[str, str] | None = None, worker_prefix: tuple[str, ...] = (),
                metrics_port: int | None = None, storage: str = "s3", extra_env: dict[str, str] | None = None,
                ready_timeout_s: float = 180) -> Iterator[LocalStack]:
    """Start the stack in `folder` and yield it once the API answers /readyz and every one of the worker's
    `concurrency` pool processes has opened its renderer; stop every component on the way out.

    worker_env: settings of the worker only (SEASYNTH_GPUS, SEASYNTH_GL_PLATFORM); worker_prefix: a command the
    worker runs under (`nice -n 19`); storage: "s3" (moto_server on loopback) or "local" (a folder, no S3 server).
    """
    import redis

    redis_bin = find_program("redis-server", "apt-get install -y redis-server (any Redis >= 6 on PATH will do)")
    moto = find_program("moto_server", "pip install 'moto[server]'") if storage == "s3" else None
    rport, sport, aport = free_port(), free_port(), free_port()
    env = {**{k: v for k, v in os.environ.items() if not k.startswith(("SEASYNTH_", "AWS_"))},
           "SEASYNTH_REDIS_URL": f"redis://127.0.0.1:{rport}/0", "SEASYNTH_S3_BUCKET": BUCKET,
           "AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench-secret", "AWS_DEFAULT_REGION": "us-east-1",
           "PYTHONUNBUFFERED": "1", **(extra_env or {})}
    if storage == "s3":
        env.update(SEASYNTH_S3_ENDPOINT_URL=f"http://127.0.0.1:{sport}", SEASYNTH_S3_CREATE_BUCKET="true")
    else:
        env.update(SEASYNTH_STORAGE="local", SEASYNTH_LOCAL_ROOT=str(folder / "objects"))
    if api_key:
        env["SEASYNTH_API_KEYS"] = api_key
    cli = [sys.executable, "-m", "seasynth.cli"]
    worker = {**env, **(worker_env or {})}
    if metrics_port is not None:
        worker["SEASYNTH_WORKER_METRICS_PORT"] = str(metrics_port)
    argvs: dict[str, tuple[list[str], dict[str, str]]] = {
        "redis": ([redis_bin, "--port", str(rport), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                   "--maxmemory-policy", "noeviction", "--dir", str(folder)], env),
        **({"s3": ([moto, "-H", "127.0.0.1", "-p", str(sport)], env)} if moto else {}),
        "api": ([*cli, "serve", "--host", "127.0.0.1", "--port", str(aport)], env),
        "worker": ([*worker_prefix, *cli, "worker", "--concurrency", str(concurrency), "--queues", queues], worker),
    }
    stack = LocalStack(folder, env, f"http://127.0.0.1:{aport}", api_key,
                       f"http://127.0.0.1:{metrics_port}" if metrics_port is not None else None)
    procs = list[subprocess.Popen]()
    try:
        for name, (argv, penv) in argvs.items():
            with open(folder / f"{name}.log", "wb") as log:
                p = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=folder, env=penv)
            procs.append(p)
            stack.procs[name] = p
            if name == "redis":
                wait(lambda: redis.Redis(port=rport).ping(), 15, "redis-server", procs)
            elif name == "s3":
                wait(lambda: httpx.get(f"http://127.0.0.1:{sport}", timeout=2).status_code < 500, 30, "moto", procs)
        try:
            wait(lambda: httpx.get(f"{stack.api}/readyz", timeout=2).status_code == 200, 60, "the API", procs)
            wait(lambda: (folder / "worker.log").read_text(errors="replace").count(READY) >= concurrency,
                 ready_timeout_s, f"the worker's {concurrency} render processes", procs)
        except (RuntimeError, TimeoutError) as err:
            raise RuntimeError(f"{err}\napi log:\n{stack.log('api')}\nworker log:\n{stack.log('worker')}") from None
        yield stack
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
