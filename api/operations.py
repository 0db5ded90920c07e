"""What the dataset routes do, as plain functions of Services: enqueue datasets (admitted by seasynth.api.admission), report
status, cancel, purge, build manifests and fetch single frames. Uploaded assets: api.asset_store."""

from __future__ import annotations

import contextlib
import logging
import time
import uuid
from datetime import datetime, timezone
from typing import Any

from seasynth.api.admission import check_files, check_limits
from seasynth.api.deps import Services
from seasynth.api.models import DatasetCreated, DatasetLinks, DatasetPublic, ShardErrorPublic
from seasynth.service.errors import AssetError, Conflict, NotFound, RenderError, Unavailable
from seasynth.service.manifest import build_manifest
from seasynth.service.queues import TASK_FRAME, TASK_PLAN, TASK_RECONCILE, frame_queue, shard_queue
from seasynth.service.records.recovery import cancelled_key, check_redis, forget, restore, save_record
from seasynth.service.records.store import wait_reply
from seasynth.service.records.types import CANCELLED, QUEUED, RUNNING, TERMINAL, DatasetRecord
from seasynth.service.shards import (
    FRAME_PARTS,
    dataset_prefix,
    shard_count,
)
from seasynth.service.spec.dataset import DatasetSpec

log = logging.getLogger(__name__)

MANIFEST_PAGE = 1000  # shard indices per manifest page by default (each committed one is presigned)
MANIFEST_PAGE_MAX = 10_000


# --- the broker


def publish(services: Services, task: str, args: list, queue: str, **options: Any) -> None:
    """Publish a task by name; Unavailable (503, Retry-After) when the broker cannot take it."""
    import redis
    from kombu.exceptions import KombuError

    try:
        services.producer.send_task(task, args=args, queue=queue, **options)
    except (KombuError, redis.RedisError, OSError) as err:
        raise Unavailable(f"task broker unavailable: could not publish {task} ({type(err).__name__}: {err})") from err


# --- datasets


def links(dataset_id: str) -> DatasetLinks:
    base = f"/datasets/{dataset_id}"
    return DatasetLinks(self=base, manifest=f"{base}/manifest", frames=f"{base}/frames/{{index}}")


def create_dataset(services: Services, spec: DatasetSpec) -> DatasetCreated:
    """Record the dataset and publish one planner task: O(1) broker writes whatever the frame count.

    The record comes first: a planner task must find its record, or the worker drops it. When the publish
    fails the record is discarded and the answer is 503, so no client ever sees a dataset that nothing will
    render. If the API dies between the two writes, the record stays queued, and the reconciler republishes
    it once it has stalled for SEASYNTH_STALL_TIMEOUT_S (status reads, listings, `seasynth reconcile`).
    The creation record goes to the bucket first (seasynth.service.records.recovery), so a Redis that loses its data loses no
    dataset.
    """
    s = services.settings
    check_limits(spec, s)
    check_files(spec, services)
    dataset_id = uuid.uuid4().hex
    shards = shard_count(spec.frames, spec.shard_size)
    spec_json = spec.model_dump(mode="json")
    fields = dict(seed=spec.seed, code_version=s.worker_version, frames=spec.frames, shard_size=spec.shard_size,
                  shards=shards)
    now = time.time()
    save_record(services.records, services.store, dataset_id, {"spec": spec_json, **fields, "created_at": now})
    try:
        services.records.create(dataset_id, spec_json, **fields, now=now)
    except Exception:  # Redis unreachable (503): no record, and no client has the id
        _forget_unpublished(services, dataset_id)
        raise
    try:
        publish(services, TASK_PLAN, [dataset_id, 0], shard_queue(s.worker_version))
    except Unavailable:
        services.records.discard(dataset_id)
        _forget_unpublished(services, dataset_id)
        raise
    return DatasetCreated(
        id=dataset_id,
        state="queued",
        frames_total=spec.frames,
        shards_total=shards,
        code_version=s.worker_version,
        links=links(dataset_id),
    )


def _forget_unpublished(services: Services, dataset_id: str) -> None:
    """Delete the bucket record of a dataset whose creation failed: nothing may restore what no client was given."""
    try:
        forget(services.records, services.store, dataset_id)
    except Unavailable as err:
        log.warning("dataset %s: never published, but its bucket record stays (%s); a Redis restarted without "
                    "its data would restore it", dataset_id, err)


def _time(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, tz=timezone.utc)


def public(rec: DatasetRecord, now: float) -> DatasetPublic:
    """The API's view of a record. `errors` lists the failed shards the record carries, the first ERRORS_SHOWN
    (seasynth.service.records.store) by index; `shards_failed` counts them all."""
    rate = eta = None
    if rec.started_at is not None and rec.frames_done > 0:
        elapsed = (rec.finished_at or now) - rec.started_at
        if elapsed > 0:
            rate = rec.frames_done / elapsed
            eta = 0.0 if rec.state in TERMINAL else (rec.frames_total - rec.frames_done) / rate
    return DatasetPublic(
        id=rec.id,
        state=rec.state,
        frames_done=rec.frames_done,
        frames_total=rec.frames_total,
        shards_done=rec.shards_done,
        shards_failed=rec.shards_failed,
        shards_total=rec.shards_total,
        shard_size=rec.shard_size,
        attempts=rec.attempts,
        frames_per_s=rate,
        eta_s=eta,
        errors=[ShardErrorPublic(shard=i, error=e) for i, e in sorted(rec.errors.items())],
        seed=rec.seed,
        code_version=rec.code_version,
        renderer=rec.renderer,
        created_at=_time(rec.created_at),
        started_at=_time(rec.started_at),
        finished_at=_time(rec.finished_at),
        purged=rec.purged,
        restored_at=_time(rec.restored_at),
        notice=rec.notice,
        links=links(rec.id),
    )


def dataset_status(services: Services, dataset_id: str) -> DatasetPublic:
    """The record, and on the side a nudge to the reconciler when the dataset needs one. A nudge that cannot be
    published does not fail the read: the status is still true, and the next read nudges again."""
    rec = live_record(services, dataset_id)
    now = time.time()
    try:
        if (
            rec.state == RUNNING
            and rec.shards_done + rec.shards_failed == rec.shards_total
            and not services.records.is_finalising(dataset_id)
        ):
            # Every shard is in but nobody finalised (the finaliser died): let a worker reconcile.
            publish(services, TASK_RECONCILE, [dataset_id, False], shard_queue(rec.code_version))
        else:
            sweep_if_stalled(services, rec, now)
    except Unavailable as err:
        log.warning("dataset %s: reconciler not nudged, the next status read retries: %s", dataset_id, err)
    return public(rec, now)


def list_datasets(services: Services, offset: int, limit: int) -> tuple[list[DatasetPublic], int]:
    ids, total = services.records.list_ids(offset, limit)
    now, out = time.time(), []
    for i, rec in zip(ids, services.records.get_many(ids)):  # the page's records in one round trip
        try:
            if rec is None or rec.purged:  # deleted between the two reads, or lost by Redis (restored here)
                rec = live_record(services, i)
        except NotFound:
            continue
        try:
            sweep_if_stalled(services, rec, now)
        except Unavailable as err:  # as in dataset_status: the listing is still true
            log.warning("dataset %s: reconciler not nudged, the next read retries: %s", i, err)
        out.append(public(rec, now))
    return out, total


# --- the reconciler


def sweep_if_stalled(services: Services, rec: DatasetRecord, now: float, force: bool = False) -> bool:
    """Republish a live dataset's lost shards; True when a reconcile task was sent.

    A shard is pending when it is neither committed, nor failed, nor running within its lease (the hard task time
    limit). Queued messages cannot be told apart cheaply, so the sweep waits until the dataset has stalled: nothing
    started, committed or failed for SEASYNTH_STALL_TIMEOUT_S and nothing running; after a first sweep, also
    fewer messages in its shard queue than it has pending shards. Then a worker adopts missed
    commit markers and republishes the pending shards, marked to defer to a running execution; a copy of a
    shard that was only waiting in the queue is skipped once its original committed. At most once per stall
    timeout per dataset (a Redis lock), whoever triggers it: status reads or `seasynth reconcile`.
    `force` (an explicit reconcile) skips the stall and lock checks. Unavailable when the broker cannot take
    the task; the lock is given back, so the next caller tries again.
    """
    s = services.settings
    if rec.state not in (QUEUED, RUNNING):
        return False
    if not force:
        if now - rec.touched_at < s.stall_s:
            return False
        if services.records.live_running(rec.id, now, s.running_lease_s):
            return False
        # Waiting behind other datasets' backlog looks the same as lost. Once a sweep has republished the pending
        # shards, another waits until the queue cannot hold them all (some surely are not there): copies sent
        # while they may still be queued would only pile up behind the backlog, and autoscaling would count them.
        # (With no shard pending, the sweep's reconcile only finalises: nothing to pile up.)
        pending = rec.shards_total - rec.shards_done - rec.shards_failed
        if pending > 0 and services.records.swept(rec.id):
            if services.records.queue_length(shard_queue(rec.code_version)) >= pending:
                return False
        if not services.records.claim_sweep(rec.id, s.stall_s):
            return False
    try:
        publish(services, TASK_RECONCILE, [rec.id, True], shard_queue(rec.code_version))
    except Unavailable:
        if not force:
            services.records.release_sweep(rec.id)
        raise
    services.records.note_sweep(rec.id, now)
    return True


def sweep_all(services: Services, dataset_ids: list[str] | None = None) -> list[str]:
    """`seasynth reconcile`: sweep the given datasets now (force), or every live one that stalled, after
    recovering from a Redis restart since the last round (seasynth.service.records.recovery.check_redis): the datasets it restored
    from the bucket or whose executions it cut off are swept at once."""
    now = time.time()
    if dataset_ids:
        recs = [services.records.get(i) for i in dataset_ids]
        return [r.id for r in recs if sweep_if_stalled(services, r, now, force=True)]
    check = check_redis(services.records, services.store, now)
    if check.restored:  # a new Redis restores nothing: said only when Redis lost datasets
        log.warning("Redis restarted without its data: %d datasets restored from the bucket", len(check.restored))
    if check.cut_off:
        log.warning("Redis restarted: %d live datasets had shard executions cut off; their shards are published "
                    "again", len(check.cut_off))
    for i in sorted(set(check.restored) | set(check.cut_off)):
        rec = services.records.get(i)
        if rec.state in (QUEUED, RUNNING):
            sweep_if_stalled(services, rec, now, force=True)
    swept, offset = [], 0
    while True:
        ids, total = services.records.list_ids(offset, 500)
        for i in ids:
            try:
                rec = services.records.get(i)
            except NotFound:
                continue
            if sweep_if_stalled(services, rec, now):
                swept.append(i)
        offset += len(ids)
        if not ids or offset >= total:
            return swept


def live_record(services: Services, dataset_id: str) -> DatasetRecord:
    """The record of a dataset that was not deleted; NotFound for an unknown or deleted one. A dataset Redis lost
    (its data gone in a restart) is restored from the bucket first (seasynth.service.records.recovery.restore)."""
    try:
        rec = services.records.get(dataset_id)
    except NotFound:
        if not restore(services.records, services.store, dataset_id, time.time()):
            raise
        rec = services.records.get(dataset_id)
    if rec.purged:
        raise NotFound(f"no dataset {dataset_id} (it was deleted)")
    return rec


def cancel_dataset(services: Services, dataset_id: str) -> DatasetPublic:
    """Cancel at once (pending shards will be skipped); Conflict for a dataset that already finished."""
    live_record(services, dataset_id)
    # Noted in the bucket first: a dataset restored after Redis lost its data stays cancelled.
    marker = cancelled_key(services.records, dataset_id)
    services.store.put_bytes(marker, b"", "text/plain")
    try:
        state = services.records.cancel(dataset_id, time.time())
    except Exception:  # Redis unreachable (503): the client is told it is not cancelled, so the bucket says so too
        with contextlib.suppress(Exception):
            services.store.delete(marker)
        raise
    if state != CANCELLED:
        services.store.delete(marker)
        raise Conflict(f"dataset {dataset_id} already {state}; nothing to cancel (DELETE it to remove it)")
    return public(services.records.get(dataset_id), time.time())


def delete_dataset(services: Services, dataset_id: str) -> None:
    """Cancel a live dataset, delete its objects, then drop it from the listing; its record stays as a purged
    tombstone, which the API answers 404 for and workers still read (below).

    The purge is marked as begun before anything is deleted, and a worker checks that mark after writing an
    object: a write whose check missed the mark came before it, so the delete finds the object; a write whose
    check sees it is taken back out by its worker. The record says purged only once the delete is done: a delete
    the bucket fails answers 503 (Unavailable) and leaves the dataset readable, so the same request can be repeated.
    """
    live_record(services, dataset_id)
    services.records.cancel(dataset_id, time.time())
    services.records.mark_purging(dataset_id)
    services.store.delete_prefix(dataset_prefix(dataset_id))
    forget(services.records, services.store, dataset_id)  # before purged: a purged dataset is never restored
    services.records.mark_purged(dataset_id)
    services.records.unlist(dataset_id)


def reconcile_dataset(services: Services, dataset_id: str, requeue: bool) -> DatasetPublic:
    rec = live_record(services, dataset_id)
    publish(services, TASK_RECONCILE, [dataset_id, requeue], shard_queue(rec.code_version))
    return public(rec, time.time())


def manifest_page_link(dataset_id: str, start: int, limit: int) -> str:
    return f"/datasets/{dataset_id}/manifest?start={start}&limit={limit}"


def manifest(services: Services, dataset_id: str, start: int = 0, limit: int = MANIFEST_PAGE) -> dict:
    """One page of the manifest: the committed shards with index in [start, start + limit), each with a
    presigned URL. Pages cut by shard index, not by position among committed shards, so a page's contents
    never shift while shards commit; totals (frames_done, shards_done, complete) are the whole dataset's."""
    rec = live_record(services, dataset_id)
    stop = min(start + limit, rec.shards_total)
    page = build_manifest(rec, services.records.commits_between(dataset_id, start, stop), url=services.store.url)
    # build_manifest counts the shards it is given; this page is part of the whole.
    page["frames_done"] = rec.frames_done
    page["shards_done"] = rec.shards_done
    page["complete"] = rec.shards_done == rec.shards_total
    page["start"], page["limit"] = start, limit
    page["next"] = manifest_page_link(dataset_id, stop, limit) if stop < rec.shards_total else None
    page["urls_expire_s"] = services.settings.presign_expiry_s if services.settings.storage == "s3" else None
    return page


# --- single frames


def frame(services: Services, dataset_id: str, index: int, part: str) -> tuple[str, bytes]:
    """Re-render one file of one frame on a frames-queue worker; Unavailable (503) when none answers in time."""
    rec = live_record(services, dataset_id)
    if not 0 <= index < rec.frames_total:
        raise NotFound(f"dataset {dataset_id} has no frame {index} (frames 0..{rec.frames_total - 1})")
    if part not in FRAME_PARTS:
        raise NotFound(f"no frame part {part!r}")
    timeout = services.settings.frame_timeout_s
    key = services.records.reply_key(uuid.uuid4().hex)
    publish(services, TASK_FRAME, [dataset_id, index, part, key], frame_queue(rec.code_version), expires=timeout)
    got = wait_reply(services.raw_redis, key, timeout)
    if got is None:
        raise Unavailable(f"no frame worker rendered frame {index} of dataset {dataset_id} within {timeout:g} s")
    header, body = got
    if not header.get("ok"):
        raise worker_error(header, f"frame {index} of dataset {dataset_id}")
    return header["name"], body  # the worker names the file (its spec's image format decides .png or .jpg)


def worker_error(header: dict[str, Any], what: str) -> Exception:
    """The error for a frame worker's failure report, by the status it gives: 404 (no such frame or file),
    503 (no worker can serve it now: retry), 422 (the dataset's inputs cannot render it), anything else
    (an error while rendering: 502, a fault behind this server that repeating the request does not cure)."""
    status, error = header.get("status"), header.get("error", "no reason given")
    if status == 404:
        return NotFound(error)
    if status == 503:
        return Unavailable(f"{what}: {error}")
    if status == 422:
        return AssetError(f"{what}: {error}")
    return RenderError(f"{what} failed on the frame worker: {error}")
