"""Helpers of the service tests: component processes, tiny specs, waiting."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from seasynth.bench.stack import free_port  # noqa: F401 (the service tests import it from here)

BUCKET = "seasynth-test"

# Frames small enough that a shard takes well under a second on llvmpipe: the water's closed form, not its solved
# column, whose first solves (about 1-2 s a unit column, up to six new ones a frame on the 2-core CPU while a
# process's cache fills) would make every service test's first shards wait on the light model they do not test. The
# solved column through the service is test_service_e2e's physical-light test's.
TINY_SPEC: dict[str, Any] = {
    "seed": 7,
    "frames": 6,
    "shard_size": 2,
    "quality": "draft",
    "camera": {"width": 32, "height": 24},
    "terrain": {"cells": 16, "variants": 1},
    "targets": {"count": [1, 2], "assets": [{"procedural": "urchin", "variants": 1}]},
    "distractors": {"count": [1, 2], "assets": [{"procedural": "rock", "variants": 1}]},
    "water": {"solved_column": False},
}


def tiny_spec(**changes: Any) -> dict[str, Any]:
    spec = json.loads(json.dumps(TINY_SPEC))
    spec.update(changes)
    return spec


def wait_for(pred: Callable[[], Any], timeout: float, what: str, interval: float = 0.05) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            got = pred()
        except Exception:  # the component is still starting
            got = None
        if got:
            return got
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


@dataclass
class Proc:
    """A component process whose output goes to a log file."""

    name: str
    popen: subprocess.Popen
    log: Path

    def tail(self, n: int = 60) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(5)


@dataclass
class Stack:
    tmp: Path
    env: dict[str, str]
    api_url: str = ""
    api_proc: Proc | None = None  # the API the `client` fixture talks to (api_url)
    procs: list[Proc] = field(default_factory=list)

    def start(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> Proc:
        log = self.tmp / f"{name}-{len(self.procs)}.log"
        f = open(log, "wb")
        popen = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, env={**self.env, **(env or {})},
                                 cwd=self.tmp, start_new_session=True)
        f.close()
        proc = Proc(name, popen, log)
        self.procs.append(proc)
        return proc

    def seasynth(self, name: str, *args: str, env: dict[str, str] | None = None) -> Proc:
        return self.start(name, [sys.executable, "-m", "seasynth.cli", *args], env)

    def start_worker(self, concurrency: int = 1) -> Proc:
        return self.seasynth("worker", "worker", "--concurrency", str(concurrency), "--loglevel", "INFO")

    def workers(self) -> list[Proc]:
        """The running workers started by start_worker."""
        return [p for p in self.procs if p.name == "worker" and p.popen.poll() is None]

    def start_api(self, env: dict[str, str] | None = None) -> tuple[Proc, str]:
        port = free_port()
        proc = self.seasynth("api", "serve", "--host", "127.0.0.1", "--port", str(port), env=env)
        url = f"http://127.0.0.1:{port}"
        try:
            wait_for(lambda: httpx.get(f"{url}/readyz", timeout=2).status_code == 200, 30, "the API")
        except TimeoutError:
            raise RuntimeError(f"API did not start:\n{proc.tail()}") from None
        return proc, url

    def settings(self, **over: Any):
        from seasynth.service.settings import Settings

        env = {k[len("SEASYNTH_"):].lower(): v for k, v in self.env.items() if k.startswith("SEASYNTH_")}
        return Settings(**{**env, **over})


def need(binary: str) -> str:
    path = shutil.which(binary) or str(Path(sys.executable).parent / binary)
    if not os.path.exists(path):
        pytest.fail(f"{binary} is needed for the service tests (apt-get install -y redis-server; pip install "
                    f"'moto[server]')")
    return path


def wait_worker_ready(worker: Proc, processes: int, timeout: float = 60) -> None:
    """Until the worker's Celery consumer is ready and each of its pool processes has opened its renderer (from
    its log: Celery's `... ready.` line and one `render session ready` per process)."""

    def ready() -> bool:
        if worker.popen.poll() is not None:
            raise AssertionError(f"the worker exited with status {worker.popen.returncode}:\n{worker.tail()}")
        log = worker.log.read_text(errors="replace")
        return " ready." in log and log.count("render session ready") >= processes

    deadline = time.monotonic() + timeout
    while not ready():
        if time.monotonic() > deadline:
            raise AssertionError(f"worker not ready after {timeout} s:\n{worker.tail()}")
        time.sleep(0.1)


def log_size(proc: Proc) -> int:
    return proc.log.stat().st_size if proc.log.exists() else 0


def log_since(proc: Proc, offset: int) -> str:
    with open(proc.log, "rb") as f:
        f.seek(offset)
        return f.read().decode(errors="replace")


def wait_state(client: httpx.Client, dataset_id: str, states: set[str], timeout: float = 90) -> dict[str, Any]:
    last: dict[str, Any] = {}

    def done() -> bool:
        nonlocal last
        last = client.get(f"/datasets/{dataset_id}").json()
        return last.get("state") in states

    try:
        wait_for(done, timeout, f"dataset {dataset_id} to reach {states}", interval=0.2)
    except TimeoutError:
        raise AssertionError(f"dataset {dataset_id} stuck: {last}") from None
    return last
