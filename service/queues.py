"""The task contract between the API and the workers: task names, version-pinned queue names, and the periodic
reconciler that republishes what the queues lost.

Queue names carry the code version, so a worker of another version never takes a dataset's shards:
an API configured for version V publishes to V's queues, and a worker of version V consumes only those.
"""

from __future__ import annotations

import signal
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

TASK_PLAN = "seasynth.plan_dataset"  # (dataset_id, first_shard[, sweep]): publishes a batch of shard tasks
TASK_SHARD = "seasynth.render_shard"  # (dataset_id, shard_index[, sweep]); sweep: a reconciler's copy
TASK_FRAME = "seasynth.render_frame"  # (dataset_id, frame_index, part, reply_key)
TASK_RECONCILE = "seasynth.reconcile_dataset"  # (dataset_id, requeue)
TASK_PREVIEW = "seasynth.render_preview"  # (kind "preview" | "strip", spec_json, args, reply_key): the playground


def shard_queue(version: str) -> str:
    """Bulk work: planning, shards and reconciliation."""
    return f"seasynth.{version}.shards"


def frame_queue(version: str) -> str:
    """Interactive single-frame renders, kept apart from bulk work."""
    return f"seasynth.{version}.frames"


def broker_options(visibility_timeout_s: int) -> dict:
    """Kombu transport options every app on the broker must share (the shortest visibility timeout wins)."""
    return {"visibility_timeout": visibility_timeout_s}


# --- the periodic reconciler

RECONCILER_ROUND_SHARE = 0.8  # a round claims the broker for this share of the period: at most one round per period


@dataclass(frozen=True)
class ReconcileRound:
    """What one round of the periodic reconciler did."""

    swept: list[str]  # live datasets that had stalled: a worker republishes their pending shards
    manifests: list[str]  # finished datasets whose manifest.json was still unwritten: a worker writes it


def reconcile_round(services: Any, every_s: float, sweep: Callable[[], list[str]]) -> ReconcileRound | None:
    """One round, unless another reconciler ran one within the last RECONCILER_ROUND_SHARE * every_s (None).

    `services` is the API's (records, producer); `sweep` sweeps every stalled live dataset (seasynth.api.operations.sweep_all),
    each at most once per stall timeout whoever asks (a per-dataset lock), so the round lock only spares work:
    rounds of several reconcilers racing are still safe. Then each dataset left in the set of pending manifests
    (seasynth.service.records.coordination) gets a reconcile task, which writes its manifest.
    """
    from seasynth.service.errors import NotFound

    records = services.records
    ttl_ms = max(1, int(every_s * RECONCILER_ROUND_SHARE * 1000))
    if not records.claim_reconciler_round(ttl_ms, time.time()):
        return None
    swept = sweep()
    manifests = []
    for dataset_id in sorted(records.pending_manifests()):
        if records.is_finalising(dataset_id):  # a finaliser holds it now
            continue
        try:
            version = records.get(dataset_id).code_version
        except NotFound:
            records.drop_pending_manifest(dataset_id)
            continue
        services.producer.send_task(TASK_RECONCILE, args=[dataset_id, False], queue=shard_queue(version))
        manifests.append(dataset_id)
    return ReconcileRound(swept=swept, manifests=manifests)


def alive_file() -> Path:
    """The file the periodic reconciler touches after each round (its container's health check reads the age)."""
    return Path(tempfile.gettempdir()) / "seasynth-reconciler.alive"


def run_reconciler(
    services: Any,
    every_s: float,
    sweep: Callable[[], list[str]],
    *,
    stop: threading.Event | None = None,
    echo: Callable[[str], None] = print,
    alive: Path | None = None,
) -> None:
    """`seasynth reconcile --every SECONDS`: a round every `every_s` until `stop` is set (SIGTERM and SIGINT set it
    when this runs in the main thread). A round that fails (Redis or the broker away) is reported and the next one
    tries again; after each round that completes, `alive` (default alive_file()) is touched. Any number of
    reconcilers may run at once (see reconcile_round)."""
    if every_s <= 0:
        raise ValueError(f"every_s must be > 0, got {every_s}")
    stop = stop or threading.Event()
    alive = alive or alive_file()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    echo(f"reconciler: a round every {every_s:g} s")
    while not stop.is_set():
        started = time.monotonic()
        try:
            done = reconcile_round(services, every_s, sweep)
        except Exception as err:  # noqa: BLE001 - reported; the next round retries
            echo(f"reconciler: round failed, next in {every_s:g} s: {type(err).__name__}: {err}")
        else:
            if done is not None:
                for dataset_id in done.swept:
                    echo(f"{dataset_id}: pending shards sent to a worker to publish again")
                for dataset_id in done.manifests:
                    echo(f"{dataset_id}: manifest sent to a worker to write")
            alive.touch()
        stop.wait(max(0.0, every_s - (time.monotonic() - started)))
    echo("reconciler: stopped")
