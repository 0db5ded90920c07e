"""Prometheus metrics of a render worker: shards and frames by outcome, frame render and upload times.

Celery's prefork pool runs tasks in child processes that it recycles (worker_max_tasks_per_child, the memory
limit), so each child writes its samples to files in one folder (prometheus_client's multiprocess mode) and the
worker's main process serves their sum on SEASYNTH_WORKER_METRICS_PORT. The counts of recycled children stay in
the sum, so counters never go back. prometheus_client is imported only after the folder is set (it picks its
multiprocess value class at import).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from seasynth.service.settings import Settings

MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"  # prometheus_client's only way to be told the folder
# Seconds: a draft frame takes milliseconds on a GPU, a high-quality 4K frame tens of seconds on llvmpipe.
RENDER_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
UPLOAD_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 120.0)


class WorkerMetrics:
    """This process's metrics. Built in each pool process after the fork, registered nowhere: in multiprocess
    mode the main process's exporter reads every process's files."""

    def __init__(self) -> None:
        from prometheus_client import Counter, Histogram

        self.shards = Counter("seasynth_worker_shards", "Shard task executions by how they ended (committed, "
                              "failed: the shard was marked failed, retry: an attempt failed with attempts left, "
                              "and the other outcomes of seasynth.worker.queue.context.Outcome)", ["outcome"], registry=None)
        self.frames = Counter("seasynth_worker_frames", "Frames of the shards this worker committed (committed) "
                              "or marked failed (failed)", ["outcome"], registry=None)
        self.render_seconds = Histogram("seasynth_worker_frame_render_seconds", "Rendering one frame's files "
                                        "(shards and single-frame requests)", buckets=RENDER_BUCKETS, registry=None)
        self.upload_seconds = Histogram("seasynth_worker_upload_seconds", "One object written to the bucket: "
                                        "file (shard tars, export parts) or bytes (commit markers, manifests)",
                                        ["kind"], buckets=UPLOAD_BUCKETS, registry=None)


class TimedFrames:
    """A FrameSource (seasynth.worker.queue.context) that times each frame into `metrics` and counts the frames it rendered."""

    def __init__(self, source: Any, metrics: WorkerMetrics):
        self.source = source
        self.metrics = metrics
        self.rendered = 0  # frames rendered by this process so far

    @property
    def renderer_name(self) -> str:
        return self.source.renderer_name

    def frame_files(self, spec: Any, index: int) -> dict[str, bytes]:
        started = time.perf_counter()
        files = self.source.frame_files(spec, index)
        self.metrics.render_seconds.observe(time.perf_counter() - started)
        self.rendered += 1
        return files

    def __getattr__(self, name: str) -> Any:  # anything else the session offers, unchanged
        return getattr(self.source, name)


class TimedStore:
    """An ObjectStore (seasynth.service.storage) whose writes are timed into `metrics`; reads and the rest pass through."""

    def __init__(self, store: Any, metrics: WorkerMetrics):
        self.store = store
        self.metrics = metrics

    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None:
        with self.metrics.upload_seconds.labels("file").time():
            self.store.put_file(key, path, content_type)

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        with self.metrics.upload_seconds.labels("bytes").time():
            self.store.put_bytes(key, data, content_type)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.store, name)


@contextlib.contextmanager
def exporter(settings: Settings) -> Iterator[int | None]:
    """Serve the sum of this worker's pool processes' metrics on settings.worker_metrics_port (all interfaces)
    while the block runs; yields the port, or None when the port is not set (no exporter, nothing changed).

    Enter before the pool forks and before anything imports prometheus_client: the folder is handed to it, and
    to the pool processes, through the environment. A folder given in settings is emptied first, so counts of an
    earlier run are not summed in; the default is a fresh temporary folder, removed afterwards.
    """
    if settings.worker_metrics_port is None:
        yield None
        return
    own = settings.worker_metrics_dir is None
    folder = Path(tempfile.mkdtemp(prefix="seasynth-metrics-")) if own else Path(settings.worker_metrics_dir)
    folder.mkdir(parents=True, exist_ok=True)
    for stale in folder.glob("*.db"):
        stale.unlink()
    os.environ[MULTIPROC_ENV] = str(folder)
    from prometheus_client import CollectorRegistry, start_http_server, values
    from prometheus_client.multiprocess import MultiProcessCollector

    if not values.ValueClass._multiprocess:
        raise RuntimeError("prometheus_client was imported before the worker set PROMETHEUS_MULTIPROC_DIR: its "
                           "metrics would stay in each pool process and never reach the exporter")
    registry = CollectorRegistry()
    MultiProcessCollector(registry, path=str(folder))
    server, thread = start_http_server(settings.worker_metrics_port, registry=registry)
    try:
        yield settings.worker_metrics_port
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)
        if own:
            shutil.rmtree(folder, ignore_errors=True)
