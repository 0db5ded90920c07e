"""A purge racing a worker's writes, on real Redis and the S3 server: a worker that writes between the purge's delete
and its `purged` mark takes what it wrote back out, so no object of a purged dataset survives."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable

import pytest
from test_service_plumbing import FakeSession, make_ctx, new_dataset, records  # noqa: F401 (a fixture)

from seasynth.api.deps import Services
from seasynth.api.operations import delete_dataset
from seasynth.service.records.coordination import pending_manifests_key
from seasynth.service.shards import commit_key, dataset_prefix, manifest_key, shard_key
from seasynth.service.storage import LocalStore, open_store
from seasynth.worker.queue.context import Outcome
from seasynth.worker.queue.shard import reconcile, run_shard


def bucket(infra, tmp_path, kind: str):
    """The S3 server's bucket, or a local folder: both stores must behave alike."""
    return open_store(infra.settings()) if kind == "s3" else LocalStore(tmp_path / "bucket")


class HookedWrites:
    """An object store that calls `before[key]()` just before writing `key` and `after[key]()` just after."""

    def __init__(self, inner, before: dict[str, Callable[[], None]] | None = None,
                 after: dict[str, Callable[[], None]] | None = None):
        self.inner, self.before, self.after = inner, before or {}, after or {}

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def _write(self, key: str, write: Callable[[], None]) -> None:
        self.before.get(key, lambda: None)()
        write()
        self.after.get(key, lambda: None)()

    def put_file(self, key, path, content_type="application/octet-stream"):
        self._write(key, lambda: self.inner.put_file(key, path, content_type))

    def put_bytes(self, key, data, content_type="application/octet-stream"):
        self._write(key, lambda: self.inner.put_bytes(key, data, content_type))


class HoldAfterDelete:
    """An object store whose delete_prefix deletes, then waits for `resume` before it returns."""

    def __init__(self, inner, deleted: threading.Event, resume: threading.Event):
        self.inner, self.deleted, self.resume = inner, deleted, resume

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def delete_prefix(self, prefix: str) -> int:
        n = self.inner.delete_prefix(prefix)
        self.deleted.set()
        assert self.resume.wait(30), "the test never resumed the purge"
        return n


@pytest.mark.parametrize("kind", ["s3", "local"])
@pytest.mark.parametrize("written, outcome, state", [
    ("shard", Outcome.CANCELLED, "cancelled"),  # a shard past its last cancel check
    ("manifest", Outcome.COMMITTED, "succeeded"),  # the manifest of a dataset its last shard completed
])
def test_an_object_written_between_the_purges_delete_and_its_mark_is_taken_back_out(
    infra, records, tmp_path, written, outcome, state, kind  # noqa: F811 (records is a fixture)
):
    store = bucket(infra, tmp_path, kind)
    ds = new_dataset(records, frames=2 if written == "manifest" else 4, shard_size=2, dataset_id=uuid.uuid4().hex)
    deleted, resume, answer = threading.Event(), threading.Event(), {}
    api = Services(settings=infra.settings(), records=records, raw_redis=None,
                   store=HoldAfterDelete(store, deleted, resume), producer=None)
    purge = threading.Thread(target=lambda: answer.update(result=delete_dataset(api, ds)))

    def purge_up_to_its_mark() -> None:
        purge.start()
        assert deleted.wait(30), "the purge never deleted"

    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    key = shard_key(ds, 0, ctx.settings.shard_compression) if written == "shard" else manifest_key(ds)
    ctx.store = HookedWrites(store, before={key: purge_up_to_its_mark})
    try:
        # The worker writes after the purge's delete and finishes before the purge marks the dataset purged.
        assert run_shard(ctx, ds, 0) is outcome
        assert deleted.is_set() and not records.get(ds).purged
    finally:
        resume.set()
        purge.join(30)
    assert not purge.is_alive()
    assert answer == {"result": None}
    assert (records.get(ds).state, records.get(ds).purged) == (state, True)
    assert [o.key for o in store.list(dataset_prefix(ds))] == []


class CountDeletes:
    """An object store that notes the keys it is asked to delete one by one."""

    def __init__(self, inner):
        self.inner, self.keys = inner, []

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def delete(self, key: str) -> None:
        self.keys.append(key)
        self.inner.delete(key)


class Killed(BaseException):
    """The process dies here (SIGKILL, OOM): nothing after this point runs."""


@pytest.mark.parametrize("kind", ["s3", "local"])
def test_a_shard_an_execution_wrote_after_the_purge_and_died_is_taken_back_by_the_next_execution(
    infra, records, tmp_path, kind  # noqa: F811 (records is a fixture)
):
    store = bucket(infra, tmp_path, kind)
    ds = new_dataset(records, frames=4, shard_size=2, dataset_id=uuid.uuid4().hex)
    api = Services(settings=infra.settings(), records=records, raw_redis=None, store=store, producer=None)
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    tar = shard_key(ds, 0, ctx.settings.shard_compression)

    def die() -> None:
        raise Killed(commit_key(ds, 0))

    # The whole purge runs just before the tar is written; the process dies right after writing its marker.
    ctx.store = HookedWrites(store, before={tar: lambda: delete_dataset(api, ds)},
                             after={commit_key(ds, 0): die})
    with pytest.raises(Killed):
        run_shard(ctx, ds, 0)
    # The purge finished before these were written, and their writer died before it could take them back.
    assert records.get(ds).purged
    assert sorted(o.key for o in store.list(dataset_prefix(ds))) == sorted([tar, commit_key(ds, 0)])
    ctx.store = deletes = CountDeletes(store)
    assert run_shard(ctx, ds, 0) is Outcome.CANCELLED  # the message, redelivered
    assert [o.key for o in store.list(dataset_prefix(ds))] == [] and deletes.keys
    # A shard that never ran wrote nothing and costs no deletes.
    deletes.keys.clear()
    assert run_shard(ctx, ds, 1) is Outcome.CANCELLED and deletes.keys == []


@pytest.mark.parametrize("kind", ["s3", "local"])
def test_a_manifest_a_dead_finaliser_wrote_after_the_purge_is_deleted_by_the_next_reconcile(
    infra, records, tmp_path, kind  # noqa: F811 (records is a fixture)
):
    store = bucket(infra, tmp_path, kind)
    ds = new_dataset(records, frames=2, shard_size=2, dataset_id=uuid.uuid4().hex)
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ctx.store = store
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED and records.get(ds).state == "succeeded"
    api = Services(settings=infra.settings(), records=records, raw_redis=None, store=store, producer=None)
    delete_dataset(api, ds)
    assert records.get(ds).purged
    # A finaliser that decided before the purge writes the manifest after the purge's delete, then dies with the
    # dataset still in the set of manifests to write.
    store.put_bytes(manifest_key(ds), b"{}", "application/json")
    records._r.sadd(pending_manifests_key(records._prefix), ds)
    records.release_finalise(ds)  # the dead finaliser's lock expires
    assert reconcile(ctx, ds) == []
    assert [o.key for o in store.list(dataset_prefix(ds))] == []
    assert ds not in records.pending_manifests()
