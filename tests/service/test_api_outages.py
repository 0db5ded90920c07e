"""The API with its broker or its bucket down, over real HTTP with real Redis and moto's S3: 503s that leave no
record, status reads that survive, purges that can be repeated."""

from __future__ import annotations

import time

import httpx
import pytest
from hardening import KEY, api, commit, new_record, serve, services, settings  # noqa: F401 (fixtures)
from service_stack import free_port, tiny_spec

from seasynth.service.errors import Unavailable
from seasynth.service.storage import S3Store


def dead_producer():
    """A Celery producer whose broker refuses connections."""
    from celery import Celery

    return Celery("dead", broker=f"redis://127.0.0.1:{free_port()}/0", set_as_current=False)


def dead_store(bucket: str) -> S3Store:
    """A bucket on an endpoint where nothing listens."""
    import boto3
    from botocore.config import Config

    cfg = Config(retries={"max_attempts": 1, "mode": "standard"}, connect_timeout=2, signature_version="s3v4")
    return S3Store(boto3.client("s3", endpoint_url=f"http://127.0.0.1:{free_port()}", config=cfg), bucket)


# --- the broker or the bucket down


def hardening_keys(services) -> set[str]:
    return set(services.records._r.scan_iter(match="hardening:ds:*"))


def test_a_dataset_the_broker_cannot_take_is_503_and_leaves_no_record(serve, services, settings):
    url = serve(producer=dead_producer())
    before_ids, before_keys = services.records.list_ids(0, 10**6), hardening_keys(services)
    bucket_records = {o.key for o in services.store.list("records/")}  # seasynth.service.records.recovery's creation records
    r = httpx.post(f"{url}/datasets", json=tiny_spec(), headers={"X-API-Key": KEY}, timeout=60)
    assert r.status_code == 503 and r.headers["retry-after"] == str(settings.retry_after_s), r.text
    assert r.json()["detail"].startswith("task broker unavailable: could not publish seasynth.plan_dataset (")
    assert services.records.list_ids(0, 10**6) == before_ids
    assert hardening_keys(services) == before_keys
    assert {o.key for o in services.store.list("records/")} == bucket_records


def test_a_dataset_redis_cannot_take_is_503_and_leaves_no_bucket_record(serve, services, settings):
    import redis

    from seasynth.service.records.store import Records

    dead = Records(redis.Redis(port=free_port(), decode_responses=True, socket_connect_timeout=2), settings.key_prefix)
    url = serve(records=dead)
    bucket_records = {o.key for o in services.store.list("records/")}
    r = httpx.post(f"{url}/datasets", json=tiny_spec(), headers={"X-API-Key": KEY}, timeout=60)
    assert r.status_code == 503 and r.headers["retry-after"] == str(settings.retry_after_s), r.text
    # The creation record written before Redis refused is gone: a Redis restarted without its data restores nothing.
    assert {o.key for o in services.store.list("records/")} == bucket_records


def test_status_reads_survive_a_broker_outage_and_retry_the_nudge(serve, services):
    url = serve(producer=dead_producer())
    headers = {"X-API-Key": KEY}
    records = services.records
    # Every shard in but not finalised: a status read publishes a reconcile, and cannot.
    done = new_record(records, frames=2)
    for i in range(2):
        records.start_attempt(done, i, 3, {"since": time.time()})
        commit(records, done, i, b"shard %d" % i)
        records.end_attempt(done, i)
    r = httpx.get(f"{url}/datasets/{done}", headers=headers)
    assert r.status_code == 200, r.text
    assert (r.json()["state"], r.json()["shards_done"], r.json()["frames_done"]) == ("running", 2, 2)
    # Stalled: the sweep claims its lock, cannot publish, and gives the lock back for the next read.
    stalled = new_record(records, frames=3, age_s=10_000)
    for path in (f"/datasets/{stalled}", "/datasets?limit=100"):
        r = httpx.get(f"{url}{path}", headers=headers)
        assert r.status_code == 200, r.text
    assert records.claim_sweep(stalled, 60)
    # Asked for explicitly, the reconcile is the answer: 503.
    r = httpx.post(f"{url}/datasets/{stalled}/reconcile", headers=headers)
    assert r.status_code == 503 and r.headers["retry-after"] == "9"
    assert "task broker unavailable" in r.json()["detail"]
    r = httpx.get(f"{url}/datasets/{done}/frames/0", headers=headers)
    assert r.status_code == 503 and "seasynth.render_frame" in r.json()["detail"]


def test_a_purge_the_bucket_fails_is_503_and_can_be_repeated(serve, services, settings):
    records = services.records
    dataset_id = new_record(records, frames=3)
    for i in range(3):
        commit(records, dataset_id, i, b"tar %d" % i, services.store)
    prefix = f"datasets/{dataset_id}/"
    keys = sorted(o.key for o in services.store.list(prefix))
    assert len(keys) == 3
    headers = {"X-API-Key": KEY}

    down = serve(store=dead_store(settings.s3_bucket))
    r = httpx.delete(f"{down}/datasets/{dataset_id}", headers=headers, timeout=60)
    assert r.status_code == 503 and r.headers["retry-after"] == "9", r.text
    assert f"s3://{settings.s3_bucket}/{prefix}" in r.json()["detail"]
    rec = records.get(dataset_id)
    assert (rec.state, rec.purged) == ("cancelled", False)  # cancelled at once; not purged: objects remain
    assert sorted(o.key for o in services.store.list(prefix)) == keys

    up = serve()
    assert httpx.get(f"{up}/datasets/{dataset_id}", headers=headers).json()["state"] == "cancelled"  # still there
    r = httpx.delete(f"{up}/datasets/{dataset_id}", headers=headers)
    assert r.status_code == 204 and r.content == b"", r.text
    assert list(services.store.list(prefix)) == []
    assert records.get(dataset_id).purged  # the tombstone workers read
    assert httpx.get(f"{up}/datasets/{dataset_id}", headers=headers).status_code == 404
    assert httpx.delete(f"{up}/datasets/{dataset_id}", headers=headers).status_code == 404


class PartialDeleteClient:
    """An S3 client whose bulk delete reports one key it could not delete (HTTP 200 with Errors)."""

    def __init__(self, keys: list[str]):
        self.keys = keys

    def get_paginator(self, name):
        keys = self.keys

        class Pages:
            def paginate(self, **kw):
                return [{"Contents": [{"Key": k, "Size": 1} for k in keys]}]

        return Pages()

    def delete_objects(self, Bucket, Delete):
        return {"Errors": [{"Key": self.keys[1], "Code": "AccessDenied", "Message": "Access Denied"}]}


def test_a_bulk_delete_that_leaves_objects_is_an_error():
    store = S3Store(PartialDeleteClient(["d/a", "d/b", "d/c"]), "bkt")
    with pytest.raises(Unavailable) as info:
        store.delete_prefix("d/")
    assert str(info.value) == "s3://bkt/d/: 1 objects not deleted, e.g. d/b (AccessDenied: Access Denied)"


def test_a_record_restored_with_committed_shards_is_swept_at_once(serve, services):
    """Redis lost a dataset of which one shard of three had committed: the status read that restores it from the
    bucket adopts that shard's marker without making the dataset look recently active, so that same read sweeps it
    (a reconcile task for the rest), not one a stall timeout later."""
    from seasynth.service.records.recovery import save_record
    from seasynth.service.shards import commit_key

    records, store = services.records, services.store
    spec = tiny_spec(frames=3, shard_size=1)
    dataset_id = new_record(records, frames=3)
    rec = records.get(dataset_id)
    save_record(records, store, dataset_id, {"spec": spec, "seed": rec.seed, "code_version": rec.code_version,
                                             "frames": 3, "shard_size": 1, "shards": 3, "created_at": rec.created_at})
    shard = commit(records, dataset_id, 0, b"tar 0", store)
    store.put_bytes(commit_key(dataset_id, 0), shard.to_json().encode())
    for key in records._r.scan_iter(match=f"{records._prefix}:ds:{dataset_id}*"):  # Redis loses the dataset
        records._r.delete(key)

    url = serve()
    r = httpx.get(f"{url}/datasets/{dataset_id}", headers={"X-API-Key": KEY})
    assert r.status_code == 200, r.text
    assert (r.json()["state"], r.json()["shards_done"], r.json()["frames_done"]) == ("queued", 1, 1)
    assert r.json()["restored_at"] is not None
    assert records.get(dataset_id).touched_at == 0.0
    assert records.swept(dataset_id)
