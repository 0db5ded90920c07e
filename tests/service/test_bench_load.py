"""bench/load.py, short and at a low rate, against the real stack: every request is answered with a status its route
declares, none fails, and the counts add up; the committed results are of the current bench."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from bench import load as bench
from service_stack import Stack, free_port, wait_worker_ready
from test_worker_robustness import isolated

RESULTS = Path(__file__).resolve().parents[2] / "bench" / "results" / "cpu"


def test_a_short_load_run_has_no_errors_and_only_declared_statuses(infra: Stack):
    rate, duration, posts = 40, 3, 5
    port = free_port()
    with isolated(infra, 8, api_keys=bench.KEY) as (env, _):
        worker = infra.seasynth("worker-load", "worker", "--concurrency", "1", "--queues", "shards",
                                env={**env, "SEASYNTH_WORKER_METRICS_PORT": str(port)})
        api, url = infra.start_api(env)
        try:
            wait_worker_ready(worker, 1)
            got = asyncio.run(bench.load(url, bench.KEY, rate, duration, posts, f"http://127.0.0.1:{port}"))
        finally:
            api.stop()
            worker.stop()
    total = rate * duration
    lists = total // bench.LIST_SHARE
    assert got["errors"] == 0, got
    assert got["kinds"]["status"]["statuses"] == {"200": total - lists}
    assert got["kinds"]["list"]["statuses"] == {"200": lists}
    assert got["post"]["statuses"] == {"202": posts} and got["post"]["errors"] == 0
    scrapes = got["kinds"]["metrics"]
    assert scrapes["requests"] >= duration and scrapes["statuses"] == {"200": scrapes["requests"]}
    # Whole shards only, and the worker's counter is read after the status was.
    rendering = got["rendering"]
    assert rendering["frames_done"] % bench.RENDERING_SPEC["shard_size"] == 0
    assert rendering["worker_frames_committed"] >= rendering["frames_done"]
    # The API counted every status read of the load phase that it answered 200.
    assert got["server_side"]["status"]["requests"] == total - lists


def test_declared_statuses_come_from_the_openapi_operations():
    spec = {"paths": {"/datasets/{id}": {"get": {"responses": {"200": {}, "404": {}, "default": {}}},
                                         "parameters": []}}}
    assert bench.declared_statuses(spec) == {("GET", "/datasets/{id}"): {200, 404}}


def test_the_committed_results_are_a_run_of_this_bench():
    result = json.loads((RESULTS / "load.json").read_text())
    assert set(result["kinds"]) == {"status", "list", "metrics"}
    assert result["rate_rps"] == 200 and result["duration_s"] >= 20
    assert (RESULTS / "load.md").read_text() == bench.table(result)
