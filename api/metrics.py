"""Prometheus metrics of the API: request latency by route template, method and status (ASGI middleware), and
the depth of this version's Celery queues and the number of listed datasets, read from Redis at scrape time."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

from fastapi import FastAPI, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from starlette.routing import Match

from seasynth.api.gate import METRICS_PATH, ASGIApp, Message, Receive, Scope, Send
from seasynth.service.queues import frame_queue, shard_queue
from seasynth.service.records.store import Records
from seasynth.service.settings import Settings

UNMATCHED = "<unmatched>"  # a path no route takes: one label value, so scanners cannot grow the series
# Latency buckets, seconds: status reads take milliseconds, frame requests up to frame_timeout_s.
REQUEST_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
# Kombu's Redis transport keeps a queue's messages of priority p in list "queue" + "\x06\x16" + p (p > 0).
PRIORITY_SEPARATOR = "\x06\x16"
PRIORITY_STEPS = (0, 3, 6, 9)


def queue_lists(queue: str) -> list[str]:
    """The Redis lists that hold `queue`'s waiting messages, one per priority step."""
    return [queue if p == 0 else f"{queue}{PRIORITY_SEPARATOR}{p}" for p in PRIORITY_STEPS]


class BrokerCollector(Collector):
    """Gauges read from Redis on each scrape: messages waiting per Celery queue of the workers' version, and the
    datasets the API lists. A Redis that does not answer gives no samples (the scrape itself still succeeds).

    `records_of` returns the app's Records, which the app opens in its lifespan, after the collector is
    registered."""

    def __init__(self, records_of: Callable[[], Records], settings: Settings):
        self.records_of = records_of
        self.queues = {"shards": shard_queue(settings.worker_version), "frames": frame_queue(settings.worker_version)}

    def describe(self) -> Iterator[GaugeMetricFamily]:
        """The families without samples (the registry checks names with it; collect would need Redis)."""
        return iter(self._families())

    def _families(self) -> tuple[GaugeMetricFamily, GaugeMetricFamily]:
        depth = GaugeMetricFamily("seasynth_queue_messages", "Messages waiting in a Celery queue (Redis LLEN summed "
                                  "over its priority lists; messages a worker holds are not counted)",
                                  labels=["queue", "kind"])
        datasets = GaugeMetricFamily("seasynth_datasets", "Datasets the API lists (GET /datasets total)")
        return depth, datasets

    def collect(self) -> Iterator[GaugeMetricFamily]:
        import redis

        depth, datasets = self._families()
        try:
            lengths, listed = self.records_of().queue_lengths_and_datasets(
                [name for queue in self.queues.values() for name in queue_lists(queue)])
        except redis.RedisError:
            return
        steps = len(PRIORITY_STEPS)
        for i, (kind, queue) in enumerate(self.queues.items()):
            depth.add_metric([queue, kind], sum(lengths[i * steps:(i + 1) * steps]))
        datasets.add_metric([], listed)
        yield depth
        yield datasets


class RequestMetrics:
    """Pure ASGI middleware timing every HTTP request to its last body byte, labelled by the route's path template
    (`/datasets/{id}`, never the id itself), method and status. Outermost, so the gate's 401 and 413 count too."""

    def __init__(self, app: ASGIApp, routes: list, histogram: Histogram):
        self.app = app
        self.routes = routes
        self.histogram = histogram

    def template(self, scope: Scope) -> str:
        route = scope.get("route")  # set by the router on the request's scope once a route matched
        if route is None:  # answered before routing (the gate): find the route it was for
            route = next((r for r in self.routes if r.matches(scope)[0] is Match.FULL), None)
        return getattr(route, "path", None) or UNMATCHED

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500  # what the server answers when the app raises before it starts a response

        async def timed(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, timed)
        finally:
            self.histogram.labels(self.template(scope), scope["method"], str(status)).observe(
                time.perf_counter() - started)


def install(app: FastAPI, settings: Settings) -> None:
    """GET /metrics (text format, out of the OpenAPI schema) and the timing middleware, on a registry of this app's
    own (several apps in one process keep apart). Call last: the middleware added last runs first."""
    registry = CollectorRegistry()
    histogram = Histogram("seasynth_api_request_seconds", "HTTP request latency to the last body byte",
                          ["route", "method", "status"], buckets=REQUEST_BUCKETS, registry=registry)
    registry.register(BrokerCollector(lambda: app.state.services.records, settings))

    @app.get(METRICS_PATH, include_in_schema=False)
    def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    app.add_middleware(RequestMetrics, routes=flat_routes(app.router.routes), histogram=histogram)


def flat_routes(routes: list) -> list:
    """The routes that answer requests, with those of included routers in their place (FastAPI 0.165 keeps an
    included router as one entry that holds the original router)."""
    flat = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        flat += flat_routes(inner.routes) if inner is not None else [route]
    return flat
