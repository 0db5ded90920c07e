"""Shard plumbing on real Redis and both object stores, with a stand-in frame source: determinism of shard tars,
exactly-once counting, the attempt counter, finalising once, reconciliation. The Celery app:
tests/service/test_worker_app.py."""

from __future__ import annotations

import io
import json
import tarfile
import threading
import time

import pytest

from seasynth.service.errors import NotFound
from seasynth.service.records.store import Records
from seasynth.service.shards import Shard, commit_key, manifest_key, shard_at, shard_count, shard_key
from seasynth.service.storage import LocalStore, open_store
from seasynth.worker.queue.context import Outcome, RetryShard, ShardContext
from seasynth.worker.queue.finalise import maybe_finalise
from seasynth.worker.queue.packing import pack_tar
from seasynth.worker.queue.shard import reconcile, run_shard


class FakeSession:
    """Frame files as a pure function of (seed, index), or an error on every call."""

    renderer_name = "fake renderer 1.0"

    def __init__(self, fail: Exception | None = None):
        self.fail = fail
        self.calls: list[int] = []

    def frame_files(self, spec, index):
        self.calls.append(index)
        if self.fail is not None:
            raise self.fail
        n = f"{index:06d}"
        return {f"image_2/{n}.png": f"png {spec.seed} {index}".encode() * 3, f"calib/{n}.txt": b"P0: 1\n",
                f"label_2/{n}.txt": b""}


@pytest.fixture
def records(infra):
    import redis

    settings = infra.settings()
    r = redis.Redis.from_url(settings.redis_url, decode_responses=True)
    yield Records(r, prefix=f"unit{time.monotonic_ns()}")
    r.close()


def make_ctx(infra, records, tmp_path, session, **settings) -> ShardContext:
    import redis

    s = infra.settings(storage="local", local_root=tmp_path / "store", max_attempts=3, **settings)
    return ShardContext(settings=s, records=records, raw_redis=redis.Redis.from_url(s.redis_url),
                        store=LocalStore(s.local_root), session=session)


def new_dataset(records: Records, frames: int = 5, shard_size: int = 2, dataset_id: str = "a" * 32) -> str:
    from seasynth.service import __version__

    spec = {"seed": 3, "frames": frames, "shard_size": shard_size, "camera": {"width": 32, "height": 24}}
    records.create(dataset_id, spec, seed=3, code_version=__version__, frames=frames, shard_size=shard_size,
                   shards=shard_count(frames, shard_size), now=time.time())
    return dataset_id


@pytest.mark.parametrize("frames, size", [(1, 1), (7, 2), (10, 5), (10, 3), (3, 10)])
def test_shards_cover_every_frame_exactly_once(frames, size):
    shards = [shard_at(frames, size, i) for i in range(shard_count(frames, size))]
    assert [f for s in shards for f in s.frames] == list(range(frames))
    assert all(0 < s.frame_count <= size for s in shards)
    with pytest.raises(ValueError):
        shard_at(frames, size, len(shards))


@pytest.mark.parametrize("compression", ["none", "gz"])
def test_shard_tar_is_a_pure_function_of_its_files(compression):
    files = [("image_2/000004.png", b"\x89PNG..."), ("label_2/000004.txt", b""), ("calib/000005.txt", b"P2")]
    a, b = io.BytesIO(), io.BytesIO()
    sha_a, size_a = pack_tar(iter(files), a, compression)
    time.sleep(1.1)  # a different clock second must not change a byte
    sha_b, _ = pack_tar(iter(files), b, compression)
    assert a.getvalue() == b.getvalue() and sha_a == sha_b and size_a == len(a.getvalue())
    with tarfile.open(fileobj=io.BytesIO(a.getvalue()), mode="r:*") as tar:
        members = tar.getmembers()
        assert [(m.name, tar.extractfile(m).read()) for m in members] == files
        assert {(m.mtime, m.uid, m.gid, m.uname, m.mode) for m in members} == {(0, 0, 0, "", 0o644)}
    with pytest.raises(ValueError):
        pack_tar(iter([("../x", b"")]), io.BytesIO())


def test_shard_commits_once_and_is_skipped_after(infra, records, tmp_path):
    session = FakeSession()
    ctx = make_ctx(infra, records, tmp_path, session)
    ds = new_dataset(records)
    assert run_shard(ctx, ds, 1) is Outcome.COMMITTED
    assert session.calls == [2, 3]
    assert run_shard(ctx, ds, 1) is Outcome.ALREADY_COMMITTED and session.calls == [2, 3]
    rec = records.get(ds)
    assert (rec.frames_done, rec.shards_done, rec.attempts, rec.state) == (2, 1, 1, "running")
    marker = json.loads(ctx.store.get_bytes(commit_key(ds, 1)))
    assert marker["key"] == shard_key(ds, 1) and marker["first_frame"] == 2 and marker["frame_count"] == 2
    assert rec.renderer == "fake renderer 1.0"
    # A second commit of the same shard (a duplicate delivery) adds nothing.
    (commit,) = records.commits(ds)
    assert records.commit(ds, commit) == (False, 1, 0) and records.get(ds).frames_done == 2


def test_complete_dataset_finalises_once_with_its_manifest(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=5, shard_size=2)
    for i in range(3):
        run_shard(ctx, ds, i)
    rec = records.get(ds)
    assert (rec.state, rec.frames_done, rec.shards_done) == ("succeeded", 5, 3)
    man = json.loads(ctx.store.get_bytes(manifest_key(ds)))
    assert man["complete"] and [s["first_frame"] for s in man["shards"]] == [0, 2, 4]
    assert all("url" not in s for s in man["shards"])
    # Racing finalisers after the fact: nobody finalises again.
    results = []
    threads = [threading.Thread(target=lambda: results.append(maybe_finalise(ctx, ds))) for _ in range(8)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert results == [False] * 8


def test_racing_finalisers_write_once(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=2, shard_size=2)
    from seasynth.service.records.types import ShardCommit

    records.commit(ds, ShardCommit(0, shard_key(ds, 0), 0, 2, "0" * 64, 10, "v", "r"))
    results: list[bool] = []
    threads = [threading.Thread(target=lambda: results.append(maybe_finalise(ctx, ds))) for _ in range(8)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert sorted(results) == [False] * 7 + [True] and records.get(ds).state == "succeeded"


def test_attempt_counter_fails_a_shard_after_n_attempts(infra, records, tmp_path):
    session = FakeSession(fail=RuntimeError("GL context lost"))
    ctx = make_ctx(infra, records, tmp_path, session)
    ds = new_dataset(records, frames=2, shard_size=2)
    for attempt in (1, 2):
        with pytest.raises(RetryShard) as retry:
            run_shard(ctx, ds, 0)
        assert retry.value.countdown == 2 ** (attempt - 1)
    assert run_shard(ctx, ds, 0) is Outcome.FAILED
    rec = records.get(ds)
    assert (rec.state, rec.shards_failed, rec.attempts, rec.frames_done) == ("failed", 1, 3, 0)
    assert "gave up after 3 attempts" in rec.errors[0] and "GL context lost" in rec.errors[0]
    assert json.loads(ctx.store.get_bytes(manifest_key(ds)))["complete"] is False
    # A redelivery after that changes nothing and counts no attempt.
    assert run_shard(ctx, ds, 0) is Outcome.FAILED and records.get(ds).attempts == 3


def test_lost_attempts_count_towards_the_limit(infra, records, tmp_path):
    """Attempts whose process died (no error recorded) still use up the shard's budget."""
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=2, shard_size=2)
    for _ in range(3):
        assert records.start_attempt(ds, 0, 3, {"pid": 1}) > 0  # as if SIGKILLed mid-shard
    assert run_shard(ctx, ds, 0) is Outcome.FAILED
    assert "worker was lost" in records.get(ds).errors[0]


def test_cancelled_dataset_skips_shards(infra, records, tmp_path):
    session = FakeSession()
    ctx = make_ctx(infra, records, tmp_path, session)
    ds = new_dataset(records)
    assert records.cancel(ds, time.time()) == "cancelled"
    assert run_shard(ctx, ds, 0) is Outcome.CANCELLED and session.calls == [] and records.get(ds).attempts == 0
    assert records.cancel(ds, time.time()) == "cancelled"
    with pytest.raises(NotFound):
        records.cancel("b" * 32, time.time())
    assert run_shard(ctx, "b" * 32, 0) is Outcome.MISSING


def test_reconcile_adopts_markers_redis_lost(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=4, shard_size=2)
    run_shard(ctx, ds, 0)
    run_shard(ctx, ds, 1)
    # Redis forgets shard 1's commit and the final state (as after a restore from an old snapshot).
    records._r.srem(f"{records._prefix}:ds:{ds}:done", 1)
    records._r.hdel(f"{records._prefix}:ds:{ds}:shards", 1)
    records._r.hset(f"{records._prefix}:ds:{ds}", mapping={"state": "running", "frames_done": 2})
    records.release_finalise(ds)
    assert reconcile(ctx, ds) == []
    rec = records.get(ds)
    assert (rec.state, rec.frames_done, rec.shards_done) == ("succeeded", 4, 2)


def test_pending_shards_are_reported_for_requeue(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession())
    ds = new_dataset(records, frames=6, shard_size=2)
    run_shard(ctx, ds, 1)
    assert reconcile(ctx, ds) == [0, 2]


@pytest.mark.parametrize("kind", ["local", "s3"])
def test_object_store_contract(infra, tmp_path, kind):
    store = open_store(infra.settings(storage=kind, local_root=tmp_path / "objects"))
    prefix = f"contract-{time.monotonic_ns()}/"
    src = tmp_path / "src.bin"
    src.write_bytes(b"\x00" * 1000)
    store.put_bytes(prefix + "a/one.json", b"{}", "application/json")
    store.put_file(prefix + "a/two.bin", src)
    assert store.get_bytes(prefix + "a/one.json") == b"{}"
    assert store.head(prefix + "a/two.bin").bytes == 1000 and store.head(prefix + "nope") is None
    assert [o.key for o in store.list(prefix)] == [prefix + "a/one.json", prefix + "a/two.bin"]
    with pytest.raises(NotFound):
        store.get_bytes(prefix + "missing")
    store.download(prefix + "a/two.bin", tmp_path / "back.bin")
    assert (tmp_path / "back.bin").read_bytes() == src.read_bytes()
    assert store.url(prefix + "a/one.json").startswith("file://" if kind == "local" else "http://")
    store.check()
    # Prefixes are strings, as S3 has them: a key itself, or a key's first letters, lists that key (and its longer
    # namesakes) and nothing in its folder that does not start with them.
    store.put_bytes(prefix + "a/one.json.bak", b"[]", "application/json")
    assert [o.key for o in store.list(prefix + "a/one.json")] == [prefix + "a/one.json", prefix + "a/one.json.bak"]
    assert [o.key for o in store.list(prefix + "a/t")] == [prefix + "a/two.bin"]
    assert list(store.list(prefix + "b")) == []
    store.delete(prefix + "a/one.json.bak")
    store.delete(prefix + "a/never-written")  # deleting what is not there is not an error
    assert store.head(prefix + "a/one.json.bak") is None and store.head(prefix + "a/one.json") is not None
    assert store.delete_prefix(prefix) == 2 and list(store.list(prefix)) == []
    with pytest.raises(ValueError):
        store.put_bytes("../escape", b"")


def test_presigned_urls_use_the_public_endpoint(infra):
    store = open_store(infra.settings(s3_public_endpoint_url="http://storage.example.com:9000"))
    assert store.url("datasets/x/shards/shard-000000.tar").startswith(
        "http://storage.example.com:9000/seasynth-test/datasets/x/shards/shard-000000.tar?"
    )


def test_shard_dataclass_frames():
    assert list(Shard(3, 6, 2).frames) == [6, 7]


# --- renderers are pinned; the reconciler's view of pending shards (attempts: test_shard_attempts.py)


class NamedSession(FakeSession):
    def __init__(self, name):
        super().__init__()
        self.renderer_name = name


def test_a_dataset_keeps_the_renderer_it_started_with(infra, records, tmp_path):
    from seasynth.worker.queue.context import WrongRenderer
    from seasynth.worker.queue.shard import render_frame

    cpu, gpu = NamedSession("llvmpipe (fake)"), NamedSession("NVIDIA H100 (fake)")
    on_cpu, on_gpu = (make_ctx(infra, records, tmp_path, s) for s in (cpu, gpu))
    ds = new_dataset(records, frames=4, shard_size=2)
    assert run_shard(on_cpu, ds, 0) is Outcome.COMMITTED
    with pytest.raises(WrongRenderer, match="llvmpipe"):
        run_shard(on_gpu, ds, 1)
    rec = records.get(ds)
    assert (rec.renderer, rec.attempts, rec.shards_done) == ("llvmpipe (fake)", 1, 1) and gpu.calls == []
    with pytest.raises(WrongRenderer):
        render_frame(on_gpu, ds, 0, "image")
    header, body = render_frame(on_cpu, ds, 0, "image")
    assert header["renderer"] == "llvmpipe (fake)" and body == b"png 3 0" * 3
    assert run_shard(on_cpu, ds, 1) is Outcome.COMMITTED
    assert {c.renderer for c in records.commits(ds)} == {"llvmpipe (fake)"}

    # Two renderers racing for a fresh dataset: the first to pin it wins, the other leaves it untouched.
    ds2 = new_dataset(records, frames=2, shard_size=2, dataset_id="d" * 32)
    assert records.set_renderer(ds2, "NVIDIA H100 (fake)") == "NVIDIA H100 (fake)"
    with pytest.raises(WrongRenderer):
        run_shard(on_cpu, ds2, 0)
    assert records.get(ds2).attempts == 0 and run_shard(on_gpu, ds2, 0) is Outcome.COMMITTED


def test_pending_shards_and_running_leases(infra, records, tmp_path):
    ctx = make_ctx(infra, records, tmp_path, FakeSession(), task_time_limit_s=60)
    ds = new_dataset(records, frames=10, shard_size=2)
    run_shard(ctx, ds, 0)
    records.fail(ds, 1, "broken")
    now = time.time()
    records.start_attempt(ds, 2, 3, {"pid": 1, "since": now - 5})  # running within its lease
    records.start_attempt(ds, 3, 3, {"pid": 2, "since": now - 61})  # older than the hard limit: lost
    assert records.pending(ds, list(range(5)), now, 60) == [3, 4]
    assert records.live_running(ds, now, 60) == {2}
    assert reconcile(ctx, ds) == [3, 4]
    # A reconciler's copy leaves a shard running within its lease alone; a normal delivery does not.
    attempts = records.get(ds).attempts
    assert run_shard(ctx, ds, 2, sweep=True) is Outcome.RUNNING_ELSEWHERE and records.get(ds).attempts == attempts
    assert run_shard(ctx, ds, 3, sweep=True) is Outcome.COMMITTED


def test_sample_counts_follow_the_presets():
    """Admission's cost model (service/shards.py) knows each preset's samples per pixel."""
    from seasynth.service.shards import SAMPLES_PER_PIXEL
    from seasynth.worker.frame.function import PRESETS

    assert SAMPLES_PER_PIXEL == {name: s.per_pixel for name, s in PRESETS.items()}


HEAVY = {"quality": "draft", "camera": {"width": 640, "height": 480}, "targets": {"count": [64, 64]},
         "distractors": {"count": [64, 64]}, "terrain": {"cells": 1024},
         "outputs": {"depth": True, "instance": True, "clean": True, "range": True}}


def test_admission_costs_objects_terrain_and_outputs():
    """Each of them adds to the estimate; the heaviest accepted 640x480 draft spec is costed above what a 2-core
    CPU worker was measured to take (2.2 s per frame in the service, about 5 s per frame and process for
    `seasynth generate --workers 2` of 8 frames, every frame drawing a terrain not drawn before)."""
    from seasynth.service.shards import frame_seconds, shard_seconds, spec_cost_terms, spec_shard_seconds
    from seasynth.service.spec.dataset import parse_spec

    def cost(**changes):
        return spec_shard_seconds(parse_spec({**HEAVY, "shard_size": 4, "frames": 8, **changes}))

    heavy = cost()
    assert heavy / 4 >= 2 * 5.0, "a shard of the heavy spec must be costed at least 2x its measured time"
    assert spec_cost_terms(parse_spec(HEAVY)) == {"objects": 128, "terrain_cells": 1024, "extra_outputs": 4,
                                                  "terrain_builds": 24, "sensors": 0, "sensor_pixels": 0}
    lighter = [
        cost(targets={"count": [0, 8]}),
        cost(distractors={"count": [3, 5]}),
        cost(terrain={"cells": 256}),
        cost(terrain={"cells": 1024, "variants": 1, "styles": ["sand"]}),
        cost(outputs={"depth": False, "instance": True, "clean": True, "range": True}),
        cost(outputs={}),
    ]
    assert all(c < heavy for c in lighter), (heavy, lighter)
    # The old resolution-and-quality model is what remains with every other term at zero: 0.40 s per frame here.
    assert shard_seconds(4, 640, 480, "draft") == 4 * frame_seconds(640, 480, "draft") == pytest.approx(4 * 0.4036)
    assert heavy > 20 * shard_seconds(4, 640, 480, "draft")
    # The fewest frames that can draw them pay for terrain builds: at most one per frame.
    one = spec_shard_seconds(parse_spec({**HEAVY, "shard_size": 1, "frames": 1}))
    assert one == pytest.approx(frame_seconds(640, 480, "draft", objects=128, terrain_cells=1024, extra_outputs=4)
                                + 1024**2 * 1e-5)


def test_admission_costs_a_user_terrain_mesh_as_the_largest_grid():
    from seasynth.service.shards import MAX_TERRAIN_CELLS_COSTED, spec_cost_terms
    from seasynth.service.spec.dataset import parse_spec
    from seasynth.service.spec.scene import MAX_TERRAIN_CELLS

    spec = parse_spec({"terrain": {"cells": 16, "mesh": {"asset_id": "a" * 64}}})
    assert spec_cost_terms(spec)["terrain_cells"] == MAX_TERRAIN_CELLS_COSTED == MAX_TERRAIN_CELLS
    assert spec_cost_terms(spec)["terrain_builds"] == 1


def test_frame_memory_model_bounds_the_measured_peaks():
    """Peak RSS of one process rendering one frame with every output (llvmpipe), in GiB."""
    from seasynth.service.shards import frame_memory_bytes

    measured = {(2048, 2048, "high"): 1.65, (4096, 4096, "draft"): 2.19, (4096, 4096, "default"): 2.94,
                (4096, 4096, "high"): 5.95, (640, 480, "default"): 0.32}
    for (w, h, q), gib in measured.items():
        assert gib <= frame_memory_bytes(w, h, q) / 2**30 <= 1.5 * gib + 0.1, (w, h, q)


def test_a_record_read_leaves_its_spec_unparsed_until_asked_for(records):
    """Status reads and lists never show the spec, so reading a record does not parse it (bench/load.py); asked
    for, it is the spec the record was created with, parsed once."""
    spec = {"frames": 3, "camera": {"width": 32, "height": 24}, "targets": {"count": [1, 2]}}
    records.create("d" * 32, spec, seed=1, code_version="v", frames=3, shard_size=1, shards=3, now=time.time())
    rec = records.get("d" * 32)
    assert "spec" not in vars(rec)  # a cached_property stores its value in the instance once computed
    assert rec.spec == spec and rec.spec is rec.spec
    (listed,) = records.get_many(["d" * 32])
    assert listed.spec_json == rec.spec_json and listed.spec == spec
