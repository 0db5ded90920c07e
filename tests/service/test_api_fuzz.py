"""Schemathesis against the real API (real Redis, moto's S3, `seasynth serve`): every check, the stateful phase on,
at least 1,000 requests in a bounded time, 0 failures and no 5xx; the count comes from the API's own access log."""

from __future__ import annotations

import base64
import json
import re
import subprocess
import sys
import threading
from collections.abc import Iterator

import pytest
from service_stack import Proc, Stack

from seasynth.service.queues import TASK_PREVIEW, frame_queue
from seasynth.service.records.store import push_reply
from seasynth.service.shards import frame_file

VERSION = "0.0.0-fuzz"  # no render worker consumes these queues; the frame answerer below plays the frame worker
MIN_REQUESTS = 1000
PNG_URL = "data:image/png;base64,iVBORw0KGgo="
# The playground's renders, answered in the shape seasynth.worker.preview.playground gives them.
PREVIEW_REPLY = {
    "preview": lambda a: {"frame": a[0], "seed": 0, "width": 8, "height": 8, "images": {"image": PNG_URL},
                          "boxes": [], "render_ms": 0.0},
    "strip": lambda a: {"frames": [{"frame": a[0] + k, "image": PNG_URL} for k in range(a[1])]},
}
ACCESS = re.compile(r'"[A-Z]+ \S+ HTTP/1\.1" (\d{3})')
# The spec's cross-field rules (exactly one asset source, count ranges), configured limits and whether an upload
# decodes cannot be written in JSON Schema: a schema-valid request may still be refused with 413 or 422.
CONFIG = """
[checks.positive_data_acceptance]
expected-statuses = ["2xx", "401", "404", "409", "413", "422"]
"""


@pytest.fixture(scope="module")
def fuzz_api(infra: Stack) -> Iterator[tuple[str, Proc]]:
    proc, url = infra.start_api({"SEASYNTH_WORKER_VERSION": VERSION, "SEASYNTH_KEY_PREFIX": "fuzz",
                                 "SEASYNTH_FRAME_TIMEOUT_S": "5"})
    yield url, proc
    proc.stop()


@pytest.fixture(scope="module")
def frame_answerer(services) -> Iterator[None]:
    """Answer every frame task of VERSION's queue with a few bytes named as the worker would name them, and every
    playground render with a reply of its shape: the API's contract, not the renderer, is under test (a frame with no worker is an honest 503, tested elsewhere)."""
    raw, stop = services.raw_redis, threading.Event()

    def serve() -> None:
        while not stop.is_set():
            got = raw.blpop([frame_queue(VERSION)], timeout=1)
            if got is None:
                continue
            message = json.loads(got[1])
            args = json.loads(base64.b64decode(message["body"]))[0]
            if message["headers"]["task"] == TASK_PREVIEW:
                kind, _, task_args, reply_key = args
                push_reply(raw, reply_key, {"ok": True}, json.dumps(PREVIEW_REPLY[kind](task_args)).encode(), ttl_s=60)
                continue
            dataset_id, index, part, reply_key = args
            push_reply(raw, reply_key, {"ok": True, "name": frame_file(part, index)}, b"\x89PNG", ttl_s=60)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield
    stop.set()
    thread.join(5)


# The coverage phase is left out: Schemathesis 4.32.5 crashes inside it on this schema (SystemError: AST constructor
# recursion depth mismatch, an internal error, not a finding), which would fail the run whatever the API does.
def test_schemathesis_finds_nothing(fuzz_api, frame_answerer, tmp_path):
    url, proc = fuzz_api
    config = tmp_path / "schemathesis.toml"
    config.write_text(CONFIG)
    before = len(proc.log.read_text(errors="replace"))
    run = subprocess.run(
        [sys.executable, "-m", "schemathesis.cli", "--config-file", str(config), "run", f"{url}/openapi.json",
         "--checks", "all", "--phases", "examples,fuzzing,stateful", "--max-examples", "60",
         "--max-time", "90", "--request-timeout", "20", "--workers", "2", "--seed", "12", "--no-color"],
        capture_output=True, text=True, timeout=150,
    )
    statuses = [int(s) for s in ACCESS.findall(proc.log.read_text(errors="replace")[before:])]
    print(f"schemathesis sent {len(statuses)} requests; statuses: "
          f"{ {s: statuses.count(s) for s in sorted(set(statuses))} }")
    assert run.returncode == 0, run.stdout[-8000:] + run.stderr[-2000:]
    assert len(statuses) >= MIN_REQUESTS
    assert [s for s in statuses if s >= 500] == []
