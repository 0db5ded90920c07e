"""bench/load.py, short and at a low rate, against the real stack: every request is answered with a status its route
declares, none fails, and the counts add up; the committed results are of the current bench."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
from isolated_stacks import isolated
from service_stack import Stack, free_port, wait_worker_ready

from seasynth.bench import load as bench

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


def test_the_load_client_reads_each_kind_of_answer_and_reopens_what_the_server_closed():
    """bench.load.Http1 against a hand-written server: Content-Length and chunked bodies on one kept-alive connection,
    a new connection after Connection: close and after the server closed an idle one (its FIN read before the
    next request), and a body cut short raised, not returned."""
    heads: list[bytes] = []
    accepted: list[int] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        accepted.append(1)
        answers = {
            b"/length": b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\n\r\nhello",
            b"/chunked": b"HTTP/1.1 404 Not Found\r\nTransfer-Encoding: chunked\r\n\r\n"
                         b"3\r\nhel\r\n2;x=y\r\nlo\r\n0\r\n\r\n",
            b"/close": b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\nConnection: close\r\n\r\nok",
            b"/then-idle-close": b"HTTP/1.1 204 No Content\r\nContent-Length: 0\r\n\r\n",
            b"/cut": b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nabc",
        }
        while True:
            try:
                head = await reader.readuntil(b"\r\n\r\n")
            except asyncio.IncompleteReadError:
                break
            heads.append(head)
            target = head.split(b" ")[1]
            writer.write(answers[target])
            await writer.drain()
            if target != b"/length" and target != b"/chunked":  # each of the others ends the connection
                break
        writer.close()

    async def main() -> None:
        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        conn = bench.Http1(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", {"X-API-Key": "k"})
        try:
            assert await conn.get("/length") == (200, b"hello")
            assert await conn.get("/chunked") == (404, b"hello")
            assert len(accepted) == 1
            assert await conn.get("/close") == (200, b"ok")
            assert await conn.get("/length") == (200, b"hello") and len(accepted) == 2
            assert await conn.get("/then-idle-close") == (204, b"")
            await asyncio.sleep(0.2)  # the server's FIN arrives while the connection is idle
            assert await conn.get("/length") == (200, b"hello") and len(accepted) == 3
            with pytest.raises(EOFError):
                await conn.get("/cut")
            assert await conn.get("/length") == (200, b"hello") and len(accepted) == 4
        finally:
            conn.close()
            await asyncio.sleep(0.1)  # the handler reads the EOF and returns
            server.close()
            await server.wait_closed()

    asyncio.run(main())
    assert all(h.startswith(b"GET /") and b"\r\nX-API-Key: k\r\n" in h and b"\r\nHost: 127.0.0.1:" in h
               for h in heads) and len(heads) == 8


def test_declared_statuses_come_from_the_openapi_operations():
    spec = {"paths": {"/datasets/{id}": {"get": {"responses": {"200": {}, "404": {}, "default": {}}},
                                         "parameters": []}}}
    assert bench.declared_statuses(spec) == {("GET", "/datasets/{id}"): {200, 404}}


def test_the_committed_results_are_a_run_of_this_bench():
    result = json.loads((RESULTS / "load.json").read_text())
    assert set(result["kinds"]) == {"status", "list", "metrics"}
    assert result["rate_rps"] == 200 and result["duration_s"] >= 20
    assert (RESULTS / "load.md").read_text() == bench.table(result)
