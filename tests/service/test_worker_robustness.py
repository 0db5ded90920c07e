"""Worker robustness on real Redis: finalising against a cancel."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from service.manifest import pending_manifests_key
from service.records import Records
from service.shards import manifest_key
from service.storage import LocalStore
from test_service_plumbing import FakeSession, make_ctx, new_dataset
from worker.shard import Outcome, maybe_finalise, reconcile, run_shard


@pytest.fixture
def records(infra):
    import redis

    r = redis.Redis.from_url(infra.settings().redis_url, decode_responses=True)
    yield Records(r, prefix=f"robust{time.monotonic_ns()}")
    r.close()


# --- finalising and cancelling decide the state once, between them


class CancelOnManifest(LocalStore):
    """A bucket where a cancel arrives just as the manifest is written (the old finaliser's race window)."""

    def __init__(self, root: Path, records: Records, dataset_id: str):
        super().__init__(root)
        self.records, self.dataset_id, self.cancel_answers = records, dataset_id, []

    def put_bytes(self, key, data, content_type="application/octet-stream"):
        if key == manifest_key(self.dataset_id):
            self.cancel_answers.append(self.records.cancel(self.dataset_id, time.time()))
        super().put_bytes(key, data, content_type)


def test_a_cancel_while_the_manifest_is_written_finds_the_dataset_finished(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=4, shard_size=2)
    store = ctx.store = CancelOnManifest(tmp_path / "store", records, ds)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED and store.cancel_answers == []
    assert run_shard(ctx, ds, 1) is Outcome.COMMITTED
    # The state was decided before the manifest was written: the cancel lost, and both say succeeded.
    assert store.cancel_answers == ["succeeded"]
    rec = records.get(ds)
    manifest = json.loads(store.get_bytes(manifest_key(ds)))
    assert rec.state == manifest["state"] == "succeeded" and manifest["complete"]
    assert not records.r.sismember(pending_manifests_key(records.p), ds)


class CancelOnClaim(Records):
    """Records where a cancel arrives right after the finaliser claimed the dataset, before it decided."""

    def claim_finalise(self, dataset_id, ttl_s):
        claimed = super().claim_finalise(dataset_id, ttl_s)
        self.cancel(dataset_id, time.time())
        return claimed


def test_a_cancel_before_the_decision_leaves_no_manifest(infra, records, tmp_path):
    racing = CancelOnClaim(records.r, records.p)
    ctx = make_ctx(infra, racing, tmp_path, FakeSession())
    ds = new_dataset(racing, frames=2, shard_size=2)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED
    rec = racing.get(ds)
    assert (rec.state, rec.shards_done) == ("cancelled", 1)
    assert ctx.store.head(manifest_key(ds)) is None and not racing.r.sismember(pending_manifests_key(racing.p), ds)
    assert maybe_finalise(ctx, ds) is False and ctx.store.head(manifest_key(ds)) is None


class RefuseManifestOnce(LocalStore):
    def __init__(self, root: Path):
        super().__init__(root)
        self.refused = 0

    def put_bytes(self, key, data, content_type="application/octet-stream"):
        if key.endswith("/manifest.json") and not self.refused:
            from service.errors import Unavailable

            self.refused += 1
            raise Unavailable(f"storage unreachable writing {key}")
        super().put_bytes(key, data, content_type)


def test_a_manifest_the_bucket_refused_is_written_by_the_next_reconcile(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    store = ctx.store = RefuseManifestOnce(tmp_path / "store")
    ds = new_dataset(records, frames=2, shard_size=2)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED  # the shard's outcome stands
    assert store.refused == 1 and records.get(ds).state == "succeeded" and store.head(manifest_key(ds)) is None
    assert records.r.smembers(pending_manifests_key(records.p)) == {ds}
    assert not records.is_finalising(ds), "a failed write gives the finalise lock back"
    assert reconcile(ctx, ds) == []
    manifest = json.loads(store.get_bytes(manifest_key(ds)))
    assert manifest["state"] == "succeeded" and [s["index"] for s in manifest["shards"]] == [0]
    assert records.r.smembers(pending_manifests_key(records.p)) == set()
    assert maybe_finalise(ctx, ds) is False
