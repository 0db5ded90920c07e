"""Load on the API while a dataset renders: status reads and dataset lists at a fixed request rate, POST /datasets
throughput, and /metrics read during the run, over loopback against real components.

    seasynth bench load [--rate 200] [--duration 20] [--out bench/results/cpu]

Starts redis-server, moto's S3 server, the API (`seasynth serve`, one uvicorn process) and one render worker
(`seasynth worker --concurrency 1`, metrics on), all on this machine, so the client, the API and the renderer
share its CPUs. The client is open-loop: request i is due at start + i / rate whatever earlier ones are doing, and
its latency runs from when it was due, so a server that falls behind shows it (no coordinated omission).

The load phase's client is `Http1`: SENDERS keep-alive connections on one asyncio loop, a request a few prebuilt
bytes, an answer parsed only as far as its status and length. It replaced httpx there, whose 1.6 to 2 ms of CPU per
request on a 2-vCPU machine took a CPU from the API and left the client itself seconds behind its schedule (the
tail it measured was partly its own). Requests due go to the senders in turn, so every connection is reused about
every SENDERS / rate seconds, as a busy client's pool is, never left idle until the server's keep-alive deadline.
The setup (the schema, the rendering dataset, the sequential POSTs and their cancels) still goes through httpx.
"""

from __future__ import annotations

import asyncio
import json
import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

KEY = "bench-load-key"
# Tiny frames: the worker renders for the whole run without the renderer being what is measured.
RENDERING_SPEC: dict[str, Any] = {
    "seed": 11, "frames": 100_000, "shard_size": 20, "quality": "draft", "camera": {"width": 32, "height": 24},
    "terrain": {"cells": 16, "variants": 1},
    "targets": {"count": [1, 2], "assets": [{"procedural": "urchin", "variants": 1}]},
    "distractors": {"count": [1, 2], "assets": [{"procedural": "rock", "variants": 1}]},
}
LIST_SHARE = 5  # one request in LIST_SHARE is GET /datasets, the rest GET /datasets/{id}
# Requests in flight at most (each sender keeps one keep-alive connection busy). More requests than this wait in
# the client's own queue, still timed from when they were due.
SENDERS = 32
WORKER_NICE = 19
METRICS_EVERY_S = 1.0
REQUEST_TIMEOUT_S = 30.0


@dataclass
class Kind:
    """What one kind of request got: latencies (s, from when each was due) and statuses."""

    latencies: list[float] = field(default_factory=list)
    statuses: dict[int, int] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)  # transport errors and undeclared or 5xx statuses

    def add(self, status: int | None, latency: float, error: str | None = None) -> None:
        self.latencies.append(latency)
        if status is not None:
            self.statuses[status] = self.statuses.get(status, 0) + 1
        if error is not None:
            self.errors.append(error)

    def summary(self) -> dict[str, Any]:
        ms = sorted(x * 1e3 for x in self.latencies)
        pick = (lambda q: round(ms[min(len(ms) - 1, int(q * len(ms)))], 2)) if ms else (lambda q: None)
        return {"requests": len(ms), "errors": len(self.errors), "statuses": {str(k): v for k, v in
                sorted(self.statuses.items())}, "p50_ms": pick(0.5), "p90_ms": pick(0.9), "p99_ms": pick(0.99),
                "max_ms": round(ms[-1], 2) if ms else None, "error_examples": self.errors[:5]}


def declared_statuses(openapi: dict) -> dict[tuple[str, str], set[int]]:
    """(METHOD, path template) -> the statuses its OpenAPI operation declares."""
    return {(method.upper(), path): {int(s) for s in op["responses"] if s.isdigit()}
            for path, item in openapi["paths"].items() for method, op in item.items() if "responses" in op}


class Http1:
    """One HTTP/1.1 keep-alive connection of the load phase's client (the module docstring says why not httpx):
    a GET is a few prebuilt bytes, its answer read only as far as the status, the body (Content-Length or
    chunked) and Connection: close."""

    def __init__(self, url: str, headers: dict[str, str]):
        parts = httpx.URL(url)
        self.host, self.port = parts.host, parts.port or 80
        self.head = "".join(f"{k}: {v}\r\n" for k, v in {"Host": f"{self.host}:{self.port}", **headers}.items())
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def open(self) -> None:
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None

    async def get(self, target: str) -> tuple[int, bytes]:
        """(status, body) of GET `target`; OSError, EOFError or ValueError when the exchange fails (the connection
        is closed then, and the next request opens another)."""
        if self.reader is None or self.reader.at_eof():  # none yet, or the server closed it while it was idle
            self.close()
            await self.open()
        assert self.reader is not None and self.writer is not None
        try:
            self.writer.write(f"GET {target} HTTP/1.1\r\n{self.head}\r\n".encode("latin-1"))
            lines = (await self.reader.readuntil(b"\r\n\r\n")).decode("latin-1").split("\r\n")
            status = int(lines[0].split(" ", 2)[1])
            fields = {name.strip().lower(): value.strip() for name, _, value in
                      (line.partition(":") for line in lines[1:] if line)}
            if "content-length" in fields:
                body = await self.reader.readexactly(int(fields["content-length"]))
            elif fields.get("transfer-encoding", "").lower() == "chunked":
                body = await self._chunked()
            else:
                raise ValueError(f"a {status} answer without Content-Length or a chunked body")
        except BaseException:
            self.close()
            raise
        if fields.get("connection", "").lower() == "close":
            self.close()
        return status, body

    async def _chunked(self) -> bytes:
        assert self.reader is not None
        body = b""
        while size := int((await self.reader.readuntil(b"\r\n")).split(b";")[0], 16):
            body += (await self.reader.readexactly(size + 2))[:-2]
        await self.reader.readuntil(b"\r\n")  # no trailers are sent to a client that did not ask for them
        return body


# What a failed exchange raises: the connection refused or reset, closed mid-answer, an answer that is no HTTP.
TRANSPORT_ERRORS = (OSError, EOFError, ValueError, asyncio.LimitOverrunError)


def _check(kind: Kind, method: str, template: str, status: int, due: float, declared: dict) -> None:
    """Record an answer in `kind`: an error unless its status is declared for (method, template) and < 500."""
    allowed = declared.get((method, template), set())
    bad = status >= 500 or status not in allowed
    kind.add(status, time.perf_counter() - due,
             f"{method} {template}: {status} (declared {sorted(allowed)})" if bad else None)


async def _timed(client: httpx.AsyncClient, kind: Kind, method: str, url: str, template: str, due: float,
                 declared: dict, **kw: Any) -> httpx.Response | None:
    """One request through httpx (the sequential POSTs), recorded in `kind`."""
    try:
        r = await client.request(method, url, **kw)
    except httpx.HTTPError as err:
        kind.add(None, time.perf_counter() - due, f"{method} {template}: {type(err).__name__}: {err}")
        return None
    _check(kind, method, template, r.status_code, due, declared)
    return r


async def _timed_get(conn: Http1, kind: Kind, target: str, template: str, due: float, declared: dict) -> None:
    """One GET of the load phase, recorded in `kind` with its latency from `due`."""
    try:
        async with asyncio.timeout(REQUEST_TIMEOUT_S):
            status, _ = await conn.get(target)
    except (*TRANSPORT_ERRORS, TimeoutError) as err:
        conn.close()
        kind.add(None, time.perf_counter() - due, f"GET {template}: {type(err).__name__}: {err}")
        return
    _check(kind, "GET", template, status, due, declared)


async def _posts(client: httpx.AsyncClient, count: int, declared: dict) -> tuple[Kind, float, list[str]]:
    """POST `count` datasets one after another; (what they got, datasets/s, ids accepted)."""
    kind, ids = Kind(), []
    spec = {**RENDERING_SPEC, "frames": 10, "shard_size": 5}
    started = time.perf_counter()
    for _ in range(count):
        r = await _timed(client, kind, "POST", "/datasets", "/datasets", time.perf_counter(), declared, json=spec)
        if r is not None and r.status_code == 202:
            ids.append(r.json()["id"])
    return kind, count / (time.perf_counter() - started), ids


async def _scrapes(conn: Http1, stop: asyncio.Event, kind: Kind, declared: dict) -> None:
    """GET /metrics every METRICS_EVERY_S until `stop`, as a scraper would."""
    declared = {**declared, ("GET", "/metrics"): {200}}  # /metrics is kept out of the OpenAPI schema
    while not stop.is_set():
        await _timed_get(conn, kind, "/metrics", "/metrics", time.perf_counter(), declared)
        try:
            await asyncio.wait_for(stop.wait(), METRICS_EVERY_S)
        except asyncio.TimeoutError:
            pass


async def load(api_url: str, key: str, rate: float, duration_s: float, posts: int = 50,
               worker_metrics_url: str | None = None) -> dict[str, Any]:
    """The measurement against a running API: a dataset rendering meanwhile, `posts` sequential POSTs (then
    cancelled), then `rate` requests/s of status reads and lists for `duration_s`, with /metrics read each second."""
    headers = {"X-API-Key": key}
    async with httpx.AsyncClient(base_url=api_url, headers=headers, timeout=REQUEST_TIMEOUT_S) as client:
        declared = declared_statuses((await client.get("/openapi.json")).json())
        r = await client.post("/datasets", json=RENDERING_SPEC)
        r.raise_for_status()
        rendering = r.json()["id"]
        post_kind, post_rate, ids = await _posts(client, posts, declared)
        for i in ids:
            (await client.post(f"/datasets/{i}/cancel")).raise_for_status()
        kinds = {"status": Kind(), "list": Kind(), "metrics": Kind()}
        # The load phase's connections, opened before it (the sequential POSTs use httpx, not these).
        conns = [Http1(api_url, headers) for _ in range(SENDERS + 1)]
        await asyncio.gather(*(c.open() for c in conns))
        before = (await client.get("/metrics")).text
        stop = asyncio.Event()
        scraper = asyncio.create_task(_scrapes(conns[-1], stop, kinds["metrics"], declared))
        total = int(rate * duration_s)
        due_queue: asyncio.Queue = asyncio.Queue()
        targets = ids + [rendering]

        async def sender(conn: Http1) -> None:
            while (item := await due_queue.get()) is not None:
                i, due = item
                if i % LIST_SHARE == LIST_SHARE - 1:
                    await _timed_get(conn, kinds["list"], "/datasets?limit=20", "/datasets", due, declared)
                else:
                    await _timed_get(conn, kinds["status"], f"/datasets/{targets[i % len(targets)]}",
                                     "/datasets/{id}", due, declared)

        senders = [asyncio.create_task(sender(c)) for c in conns[:SENDERS]]
        start = time.perf_counter() + 0.05
        late = 0.0
        for i in range(total):
            due = start + i / rate
            await asyncio.sleep(max(0.0, due - time.perf_counter()))  # also yields to the senders when late
            late = max(late, time.perf_counter() - due)
            due_queue.put_nowait((i, due))
        for _ in senders:
            due_queue.put_nowait(None)
        await asyncio.gather(*senders)
        elapsed = time.perf_counter() - start
        stop.set()
        await scraper
        for c in conns:
            c.close()
        after = (await client.get("/metrics")).text  # every request of the load phase answered by now
        status = (await client.get(f"/datasets/{rendering}")).json()
        (await client.post(f"/datasets/{rendering}/cancel")).raise_for_status()
    worker_frames = None
    if worker_metrics_url is not None:
        # A labelled counter has no sample until its first increment: none means none committed yet.
        worker_frames = _sample(httpx.get(worker_metrics_url, timeout=10).text, "seasynth_worker_frames_total",
                                outcome="committed") or 0.0
    return {
        "rate_rps": rate, "duration_s": duration_s, "achieved_rps": round(total / elapsed, 1),
        "client_max_late_ms": round(late * 1e3, 2),
        "kinds": {k: v.summary() for k, v in kinds.items()},
        "errors": sum(len(v.errors) for v in [*kinds.values(), post_kind]),
        "post": {**post_kind.summary(), "datasets_per_s": round(post_rate, 1)},
        "rendering": {"frames_done": status["frames_done"], "state": status["state"],
                      "worker_frames_committed": worker_frames},
        # The API's own view (its latency histogram, from the request's arrival to its last byte) of the load phase.
        "server_side": {name: _bucket_quantiles(before, after, route) for name, route in
                        (("status", "/datasets/{id}"), ("list", "/datasets"))},
    }


def _buckets(text: str, route: str) -> dict[float, float]:
    """Cumulative bucket counts of seasynth_api_request_seconds for GET `route` answered 200: le -> count."""
    from prometheus_client.parser import text_string_to_metric_families

    return {float(s.labels["le"]): s.value for family in text_string_to_metric_families(text) for s in family.samples
            if s.name == "seasynth_api_request_seconds_bucket" and s.labels.get("route") == route
            and s.labels.get("method") == "GET" and s.labels.get("status") == "200"}


def _bucket_quantiles(before: str, after: str, route: str) -> dict[str, Any]:
    """Requests between two scrapes, and the upper bounds (ms) of the buckets holding their p50 and p99."""
    a, b = _buckets(after, route), _buckets(before, route)
    delta = sorted((le, n - b.get(le, 0.0)) for le, n in a.items())
    total = delta[-1][1] if delta else 0
    bound = lambda q: next((le * 1e3 for le, n in delta if n >= q * total), None) if total else None  # noqa: E731
    return {"requests": int(total), "p50_ms_at_most": bound(0.5), "p99_ms_at_most": bound(0.99)}


def _sample(text: str, name: str, **labels: str) -> float | None:
    from prometheus_client.parser import text_string_to_metric_families

    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == name and s.labels == labels:
                return s.value
    return None


def table(result: dict[str, Any]) -> str:
    rows = ["| requests | rate (rps) | count | errors | p50 ms | p90 ms | p99 ms | max ms |",
            "|---|---|---|---|---|---|---|---|"]
    names = {"status": "GET /datasets/{id}", "list": "GET /datasets?limit=20", "metrics": "GET /metrics (1/s)"}
    for k, name in names.items():
        s = result["kinds"][k]
        rate = result["achieved_rps"] if k != "metrics" else "-"
        rows.append(f"| {name} | {rate} | {s['requests']} | {s['errors']} | {s['p50_ms']} | {s['p90_ms']} | "
                    f"{s['p99_ms']} | {s['max_ms']} |")
    p = result["post"]
    rows.append(f"| POST /datasets (sequential) | {p['datasets_per_s']} | {p['requests']} | {p['errors']} | "
                f"{p['p50_ms']} | {p['p90_ms']} | {p['p99_ms']} | {p['max_ms']} |")
    r = result["rendering"]
    return "\n".join([
        "# Load: the API under status reads and lists while a dataset renders", "",
        f"machine: {result['machine']}  ",
        f"{result['rate_rps']} requests/s offered for {result['duration_s']} s ({result['achieved_rps']} achieved; one "
        f"in {LIST_SHARE} a list) over {SENDERS} keep-alive connections of a lean asyncio HTTP/1.1 client, open loop: "
        f"latency from when each request was due (client at most {result['client_max_late_ms']} ms late). API: one "
        f"uvicorn process; one worker rendering meanwhile "
        f"({r['frames_done']} frames committed during the run, {r['worker_frames_committed']} by its metrics). "
        f"Errors: transport errors, 5xx, or a status the route does not declare: {result['errors']}.", "",
        *rows, "",
        "The API's own view (seasynth_api_request_seconds, arrival to last byte, so without the time a request "
        "waited for a connection; bucket bounds): " + "; ".join(
            f"{name}: p50 <= {v['p50_ms_at_most']} ms, p99 <= {v['p99_ms_at_most']} ms of {v['requests']}"
            for name, v in result["server_side"].items()) + ".", ""])


def run(rate: float = 200, duration_s: float = 20, posts: int = 50, out: Path | None = None,
        machine: str | None = None) -> dict[str, Any]:
    """Start the stack, measure, print the table, and write load.json and load.md to `out` when given."""
    import signal

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # stop the components on the way out, too
    from seasynth.bench.stack import free_port, local_stack

    # The worker is niced: on a machine this small the renderer would otherwise take the CPU the API is measured on
    # (where they are deployed, the API and the workers have CPUs of their own).
    with tempfile.TemporaryDirectory(prefix="seasynth-load-") as tmp, local_stack(
            Path(tmp), api_key=KEY, worker_prefix=("nice", "-n", str(WORKER_NICE)), metrics_port=free_port()) as st:
        result = asyncio.run(load(st.api, KEY, rate, duration_s, posts, st.worker_metrics))
    result["machine"] = machine or f"{platform.node()} ({os.cpu_count()} CPUs, {platform.machine()})"
    text = table(result)
    print(text)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "load.json").write_text(json.dumps(result, indent=2) + "\n")
        (out / "load.md").write_text(text)
    return result
