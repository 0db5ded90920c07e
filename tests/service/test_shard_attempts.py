"""A shard's attempts: every failure is counted and bounded, and the commit marker a shard looks for before it
uploads (one Redis may have missed) is read while its frames render, never after an upload."""

from __future__ import annotations

import threading

import pytest
from test_service_plumbing import FakeSession, make_ctx, new_dataset, records  # noqa: F401 (a fixture)

from seasynth.service import __version__
from seasynth.service.errors import AssetError
from seasynth.service.records.store import Records
from seasynth.service.records.types import ShardCommit
from seasynth.service.shards import commit_key, manifest_key, shard_key
from seasynth.service.storage import LocalStore
from seasynth.worker.queue.context import Outcome, RetryShard
from seasynth.worker.queue.shard import run_shard
from seasynth.worker.scene.sample import SceneError


def stored(tmp_path) -> list[str]:
    return sorted(str(p.relative_to(tmp_path)) for p in (tmp_path / "store").rglob("*") if p.is_file())


class FlakyRecords(Records):
    """Records whose first `is_committed` fails as if Redis dropped the connection."""

    def __init__(self, r, prefix):
        super().__init__(r, prefix)
        self.failures = 1

    def is_committed(self, dataset_id, index):
        if self.failures:
            self.failures -= 1
            import redis

            raise redis.ConnectionError("Connection reset by peer")
        return super().is_committed(dataset_id, index)


class UnreachableStore(LocalStore):
    """A bucket that answers no read (an S3 outage)."""

    def get_bytes(self, key):
        from seasynth.service.errors import Unavailable

        raise Unavailable(f"storage unreachable reading {key}")


def test_failures_before_the_render_are_counted_and_bounded(infra, records, tmp_path):
    """A failure anywhere in the task uses an attempt and ends in a retry or a failed shard, never a lost one."""
    session = FakeSession()
    ctx = make_ctx(infra, records, tmp_path, session)
    ctx.store = UnreachableStore(tmp_path / "store")
    ds = new_dataset(records, frames=2, shard_size=2)
    for attempt in (1, 2):
        with pytest.raises(RetryShard) as retry:
            run_shard(ctx, ds, 0)  # reading the commit marker fails
        assert retry.value.countdown == 2 ** (attempt - 1) and "Unavailable" in str(retry.value)
    assert run_shard(ctx, ds, 0) is Outcome.FAILED
    rec = records.get(ds)
    assert (rec.attempts, rec.shards_failed, rec.state) == (3, 1, "failed")
    # Frames may have rendered meanwhile, but no tar and no marker are uploaded without the read: only the failed
    # dataset's manifest.
    assert stored(tmp_path) == [f"store/{manifest_key(ds)}"]
    assert "gave up after 3 attempts" in rec.errors[0] and "storage unreachable" in rec.errors[0]
    assert records.running(ds) == {}

    # Redis failing before the attempt started: counted as well, then the shard renders.
    flaky = FlakyRecords(records._r, records._prefix)
    ctx = make_ctx(infra, flaky, tmp_path, FakeSession())
    ds = new_dataset(flaky, frames=2, shard_size=2, dataset_id="c" * 32)
    with pytest.raises(RetryShard) as retry:
        run_shard(ctx, ds, 0)
    assert "ConnectionError" in str(retry.value) and flaky.get(ds).attempts == 1
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED
    assert (flaky.get(ds).attempts, flaky.get(ds).state) == (2, "succeeded")


class FrameSignal(FakeSession):
    """A frame source that says when its first frame has begun."""

    def __init__(self, fail: Exception | None = None):
        super().__init__(fail)
        self.begun = threading.Event()

    def frame_files(self, spec, index):
        self.begun.set()
        return super().frame_files(spec, index)


class MarkerAfterFrame(LocalStore):
    """A bucket whose reads answer only once a frame has begun, or after 10 s (a read the shard waited for)."""

    def __init__(self, root, begun: threading.Event):
        super().__init__(root)
        self.begun = begun
        self.overlapped: bool | None = None

    def get_bytes(self, key):
        self.overlapped = self.begun.wait(10)
        return super().get_bytes(key)


def test_the_marker_is_read_while_the_frames_render(infra, records, tmp_path):
    session = FrameSignal()
    ctx = make_ctx(infra, records, tmp_path, session)
    ctx.store = MarkerAfterFrame(tmp_path / "store", session.begun)
    ds = new_dataset(records, frames=2, shard_size=2)
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED
    assert ctx.store.overlapped is True and session.calls == [0, 1]
    rec = records.get(ds)
    assert (rec.state, rec.frames_done, rec.attempts, rec.errors) == ("succeeded", 2, 1, {})
    assert stored(tmp_path) == sorted(f"store/{k}" for k in (commit_key(ds, 0), shard_key(ds, 0), manifest_key(ds)))


@pytest.mark.parametrize("fail", [None, RuntimeError("a frame failed")], ids=["frames-render", "a-frame-fails"])
def test_a_marker_redis_missed_is_adopted_and_nothing_uploaded_over_it(infra, records, tmp_path, fail):
    """Found before, during or after the frames (or while a frame fails), a marker commits the shard: the tar it
    names is not written again and the attempt records no error."""
    session = FakeSession(fail)
    ctx = make_ctx(infra, records, tmp_path, session)
    ds = new_dataset(records, frames=4, shard_size=2)
    marker = ShardCommit(1, shard_key(ds, 1), 2, 2, "0" * 64, 10, __version__, session.renderer_name)
    ctx.store.put_bytes(commit_key(ds, 1), marker.to_json().encode())
    assert run_shard(ctx, ds, 1) is Outcome.ALREADY_COMMITTED
    rec = records.get(ds)
    assert (rec.state, rec.frames_done, rec.shards_done, rec.attempts, rec.errors) == ("running", 2, 1, 1, {})
    assert stored(tmp_path) == [f"store/{commit_key(ds, 1)}"] and records.running(ds) == {}


def test_a_shard_whose_last_attempt_wrote_its_marker_is_committed_not_given_up(infra, records, tmp_path):
    """Every attempt was lost (the worker killed), the last one after its marker was written and before Redis
    counted it: the execution that finds no attempt left adopts the marker instead of failing the shard."""
    session = FakeSession()
    ctx = make_ctx(infra, records, tmp_path, session)
    ds = new_dataset(records, frames=4, shard_size=2)
    for _ in range(ctx.settings.max_attempts):
        records.start_attempt(ds, 1, ctx.settings.max_attempts, {"since": 0.0})
        records.end_attempt(ds, 1)
    marker = ShardCommit(1, shard_key(ds, 1), 2, 2, "0" * 64, 10, __version__, session.renderer_name)
    ctx.store.put_bytes(commit_key(ds, 1), marker.to_json().encode())
    assert run_shard(ctx, ds, 1) is Outcome.ALREADY_COMMITTED
    rec = records.get(ds)
    assert (rec.state, rec.shards_done, rec.shards_failed, rec.frames_done, rec.errors) == ("running", 1, 0, 2, {})
    assert session.calls == []
    assert run_shard(ctx, ds, 0) is Outcome.COMMITTED and records.get(ds).state == "succeeded"
    # Without a marker, the execution that finds no attempt left gives the shard up.
    other = new_dataset(records, frames=2, shard_size=2, dataset_id="d" * 32)
    for _ in range(ctx.settings.max_attempts):
        records.start_attempt(other, 0, ctx.settings.max_attempts, {"since": 0.0})
        records.end_attempt(other, 0)
    assert run_shard(ctx, other, 0) is Outcome.FAILED
    assert (records.get(other).state, records.get(other).shards_failed) == ("failed", 1)


def test_a_failed_shard_whose_marker_turns_up_is_counted_once_as_committed(records):
    """A reconcile that adopts the marker of a shard already given up: done, no longer failed, its error gone, so
    done + failed never reaches the shard total early."""
    ds = new_dataset(records, frames=6, shard_size=2)
    records.fail(ds, 1, "gave up after 3 attempts")
    records.fail(ds, 2, "gave up after 3 attempts")
    rec = records.get(ds)
    assert (rec.shards_failed, sorted(rec.errors)) == (2, [1, 2])
    marker = ShardCommit(1, shard_key(ds, 1), 2, 2, "0" * 64, 10, __version__, "r")
    assert records.commit(ds, marker) == (True, 1, 1)
    assert records.commit(ds, marker) == (False, 1, 1)  # once
    rec = records.get(ds)
    assert (rec.shards_done, rec.shards_failed, rec.frames_done, sorted(rec.errors)) == (1, 1, 2, [2])
    assert records.fail(ds, 1, "late") == (1, 1)  # a committed shard is never failed again


@pytest.mark.parametrize(("error", "status"), [
    (SceneError("workspaces.camera: no camera position outside the terrain and objects after 64 draws"), 422),
    (AssetError("terrain.mesh: seabed.obj: no triangles"), 422),
    (RuntimeError("GL context lost"), 500),
], ids=["scene", "asset", "render"])
def test_a_frame_the_datasets_inputs_cannot_render_is_422_a_failed_render_500(infra, records, tmp_path, error,
                                                                             status):
    from seasynth.worker.queue.shard import frame_reply

    ctx = make_ctx(infra, records, tmp_path, FakeSession(error))
    ds = new_dataset(records, frames=4, shard_size=2)
    header, body = frame_reply(ctx, ds, 1, "image")
    assert (header["ok"], header["status"], body) == (False, status, b"")
    assert header["error"] == (str(error) if status == 422 else f"RuntimeError: {error}")
    assert frame_reply(ctx, ds, 9, "image")[0]["status"] == 404
