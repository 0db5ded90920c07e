"""Dataset and shard status records in Redis: our own source of truth (never Celery's result backend).

Keys (P = settings.key_prefix):
  P:datasets          ZSET  dataset id -> creation time (ms), for newest-first listing
  P:ds:{id}           HASH  the dataset record (spec, seed, versions, state, counters, times)
  P:ds:{id}:done      SET   committed shard indices (SADD makes a retry's commit count once)
  P:ds:{id}:failed    SET   shard indices given up on
  P:ds:{id}:shards    HASH  shard index -> commit record JSON (key, sha256, bytes, frames, renderer, export parts)
  P:ds:{id}:tries     HASH  shard index -> executions counted against max_attempts (one that failed only because
                            the bucket was unreachable is given back: refund_attempt)
  P:ds:{id}:outages   HASH  shard index -> executions given back for an outage (their retry backs off by it)
  P:ds:{id}:errors    HASH  shard index -> last error
  P:ds:{id}:shown     ZSET  the first ERRORS_SHOWN failed shard indices (score: the index), whose errors a record
                            carries
  P:ds:{id}:running   HASH  shard index -> JSON {pid, host, since} while a process renders it; an entry older
                            than the hard task time limit is stale (that execution is certainly over)
  P:ds:{id}:final     STR   finalise guard (SET NX with a TTL, so a finaliser that died can be replaced)
  P:ds:{id}:sweep     STR   reconciler guard: at most one sweep of a dataset per stall timeout
  P:reply:{uuid}      LIST  one single-frame answer, pushed by a worker and popped by the API
The queue side's keys (pending manifests, renderers, hand-backs, locks) are listed in coordination.py.
"""

from __future__ import annotations

import json
import time
from typing import Any

from seasynth.service.errors import NotFound
from seasynth.service.records import scripts
from seasynth.service.records.coordination import Coordination
from seasynth.service.records.types import CANCELLED, QUEUED, DatasetRecord, ShardCommit

# A record carries the errors of at most this many failed shards, those of lowest index: reading a record costs
# the same however many shards failed (shards_failed counts them all).
ERRORS_SHOWN = 20

# Every key of a dataset, for discarding one that was never published.
PARTS = ("done", "failed", "shards", "tries", "outages", "errors", "shown", "running", "final", "sweep")


def _fields(dataset_id: str, spec: dict[str, Any], seed: int, code_version: str, frames: int, shard_size: int,
            shards: int, now: float) -> dict[str, Any]:
    """A new record's hash fields."""
    return {
        "id": dataset_id,
        "created_at": repr(now),
        "spec": json.dumps(spec, sort_keys=True),
        "seed": seed,
        "code_version": code_version,
        "state": QUEUED,
        "frames_total": frames,
        "shard_size": shard_size,
        "shards_total": shards,
        "frames_done": 0,
        "attempts": 0,
        "touched_at": repr(now),
    }


class Records(Coordination):
    """Dataset records on a Redis client made with decode_responses=True: the one door to Redis (the queue side's
    coordination is the Coordination mixin's). Nothing outside seasynth.service.records touches the client, the
    prefix or the keys (tests/test_records_door.py)."""

    def __init__(self, redis, prefix: str = "seasynth"):
        self._r = redis
        self._prefix = prefix
        self._start = redis.register_script(scripts.START)
        self._commit = redis.register_script(scripts.COMMIT)
        self._fail = redis.register_script(scripts.FAIL)
        self._errors = redis.register_script(scripts.ERRORS)
        self._finish = redis.register_script(scripts.FINISH)
        self._update = redis.register_script(scripts.UPDATE)
        self._restore = redis.register_script(scripts.RESTORE)
        self._decide = redis.register_script(scripts.DECIDE)
        self._hand_back = redis.register_script(scripts.HAND_BACK)
        self._found = redis.register_script(scripts.FOUND)

    @classmethod
    def from_url(cls, url: str, prefix: str = "seasynth", **options: Any) -> Records:
        """Records on a new client of the Redis at `url` (redis-py's from_url `options`)."""
        import redis

        return cls(redis.Redis.from_url(url, decode_responses=True, **options), prefix)

    def _key(self, dataset_id: str, part: str = "") -> str:
        return f"{self._prefix}:ds:{dataset_id}" + (f":{part}" if part else "")

    # --- datasets
    def create(
        self,
        dataset_id: str,
        spec: dict[str, Any],
        *,
        seed: int,
        code_version: str,
        frames: int,
        shard_size: int,
        shards: int,
        now: float,
    ) -> None:
        fields = _fields(dataset_id, spec, seed, code_version, frames, shard_size, shards, now)
        with self._r.pipeline() as pipe:
            pipe.hset(self._key(dataset_id), mapping=fields)
            pipe.zadd(f"{self._prefix}:datasets", {dataset_id: int(now * 1000)})
            pipe.execute()

    def restore(self, dataset_id: str, spec: dict[str, Any], *, seed: int, code_version: str, frames: int,
                shard_size: int, shards: int, created_at: float, now: float) -> bool:
        """Recreate a record Redis lost (seasynth.service.records.recovery), queued, marked restored_at `now` and last touched at
        the epoch, so the reconciler sweeps it at once; False when a record exists (another restorer won)."""
        fields = _fields(dataset_id, spec, seed, code_version, frames, shard_size, shards, created_at)
        fields.update(touched_at="0", restored_at=repr(now))
        flat = [str(x) for kv in fields.items() for x in kv]
        return bool(self._restore(keys=[self._key(dataset_id), f"{self._prefix}:datasets"],
                                  args=[int(created_at * 1000), dataset_id, *flat]))

    def discard(self, dataset_id: str) -> None:
        """Remove a dataset and every key it has, as if it had never been created (one whose planner task could
        not be published)."""
        with self._r.pipeline(transaction=True) as pipe:
            pipe.zrem(f"{self._prefix}:datasets", dataset_id)
            pipe.delete(self._key(dataset_id), *(self._key(dataset_id, part) for part in PARTS))
            pipe.execute()

    def get(self, dataset_id: str) -> DatasetRecord:
        """The record, with the errors of the first ERRORS_SHOWN failed shards; NotFound for an id that names no
        dataset."""
        (raw,) = self._read([dataset_id])
        if raw is None:
            raise NotFound(f"no dataset {dataset_id}")
        return self._record(*raw)

    def get_many(self, dataset_ids: list[str]) -> list[DatasetRecord | None]:
        """The records of `dataset_ids` in one round trip (a page of GET /datasets); None for an id that names no
        dataset."""
        return [None if raw is None else self._record(*raw) for raw in self._read(dataset_ids)]

    def _read(self, dataset_ids: list[str]) -> list[tuple | None]:
        """What a record is built from, per id, in one MULTI/EXEC; None where the record's hash is absent.

        EVALSHA rather than the Script object: redis-py asks SCRIPT EXISTS before every pipeline that holds a
        Script, a second round trip on every status read. A Redis that lost the script answers NOSCRIPT: loaded
        once, then read again."""
        import redis

        for attempt in (1, 2):
            try:
                with self._r.pipeline(transaction=True) as pipe:
                    for i in dataset_ids:
                        pipe.hgetall(self._key(i))
                        pipe.scard(self._key(i, "done"))
                        pipe.scard(self._key(i, "failed"))
                        pipe.evalsha(self._errors.sha, 3, self._key(i, "failed"), self._key(i, "shown"),
                                     self._key(i, "errors"), ERRORS_SHOWN)
                    got = pipe.execute()
                break
            except redis.exceptions.NoScriptError:
                if attempt == 2:
                    raise
                self._r.script_load(scripts.ERRORS)
        raws = [tuple(got[k:k + 4]) for k in range(0, len(got), 4)]
        return [raw if raw[0] else None for raw in raws]

    def _record(self, h: dict[str, str], done: int, failed: int, errors: list[str]) -> DatasetRecord:
        opt = lambda k: float(h[k]) if h.get(k) else None  # noqa: E731
        return DatasetRecord(
            id=h["id"],
            created_at=float(h["created_at"]),
            spec_json=h["spec"],
            seed=int(h["seed"]),
            code_version=h["code_version"],
            renderer=h.get("renderer"),
            state=h["state"],
            frames_total=int(h["frames_total"]),
            shard_size=int(h["shard_size"]),
            shards_total=int(h["shards_total"]),
            frames_done=int(h["frames_done"]),
            shards_done=done,
            shards_failed=failed,
            attempts=int(h["attempts"]),
            started_at=opt("started_at"),
            finished_at=opt("finished_at"),
            touched_at=float(h.get("touched_at") or h["created_at"]),
            purged=h.get("purged") == "1",
            errors={int(i): e for i, e in zip(errors[::2], errors[1::2])},
            restored_at=opt("restored_at"),
            notice=h.get("notice") or None,
        )

    def exists(self, dataset_id: str) -> bool:
        return bool(self._r.exists(self._key(dataset_id)))

    def state(self, dataset_id: str) -> str | None:
        return self._r.hget(self._key(dataset_id), "state")

    def list_ids(self, offset: int, limit: int) -> tuple[list[str], int]:
        """Dataset ids newest first, and how many there are."""
        key = f"{self._prefix}:datasets"
        with self._r.pipeline() as pipe:
            pipe.zrevrange(key, offset, offset + limit - 1)
            pipe.zcard(key)
            ids, total = pipe.execute()
        return ids, total

    def set_renderer(self, dataset_id: str, renderer: str) -> str:
        """Record the renderer the dataset started with (first writer wins); return the recorded one."""
        self._r.hsetnx(self._key(dataset_id), "renderer", renderer)
        return self._r.hget(self._key(dataset_id), "renderer")

    def cancel(self, dataset_id: str, now: float) -> str:
        """Cancel a live dataset at once; return the state after (a finished dataset keeps its own)."""
        state = self._finish(keys=[self._key(dataset_id)], args=[CANCELLED, repr(now)])
        if state is None:
            raise NotFound(f"no dataset {dataset_id}")
        return state

    def finish(self, dataset_id: str, state: str, now: float) -> str:
        return self._finish(keys=[self._key(dataset_id)], args=[state, repr(now)])

    def mark_purging(self, dataset_id: str) -> None:
        """Note that a purge has begun: call it before deleting any object. A worker that writes an object of the
        dataset checks this afterwards (purge_started) and takes what it wrote back out."""
        self._update(keys=[self._key(dataset_id)], args=["purging", "1"])

    def mark_purged(self, dataset_id: str) -> None:
        """Note that the dataset's objects are gone: call it only after they were deleted."""
        self._update(keys=[self._key(dataset_id)], args=["purged", "1"])

    def unlist(self, dataset_id: str) -> None:
        """Drop a purged dataset from the listing. Its record stays: workers still find it purged (purge_started)
        and take back out what they write late."""
        self._r.zrem(f"{self._prefix}:datasets", dataset_id)

    def purge_started(self, dataset_id: str) -> bool:
        """Whether a purge has begun (mark_purging) or finished: an object of the dataset written before this answer
        may already have been missed by the purge's delete."""
        return "1" in self._r.hmget(self._key(dataset_id), "purging", "purged")

    def touch(self, dataset_id: str, now: float) -> None:
        """Note activity (planning, a sweep): the reconciler leaves a dataset alone for a stall timeout after."""
        self._update(keys=[self._key(dataset_id)], args=["touched_at", repr(now)])

    def note_sweep(self, dataset_id: str, now: float) -> None:
        """Note that a sweep sent the dataset's pending shards to be published again (swept_at)."""
        self._update(keys=[self._key(dataset_id)], args=["swept_at", repr(now)])

    def swept(self, dataset_id: str) -> bool:
        """Whether a sweep has sent the dataset's pending shards to be published again."""
        return bool(self._r.hexists(self._key(dataset_id), "swept_at"))

    def claim_sweep(self, dataset_id: str, ttl_s: int) -> bool:
        """True for the one caller that may sweep the dataset now; the next sweep waits ttl_s."""
        return bool(self._r.set(self._key(dataset_id, "sweep"), "1", nx=True, ex=max(1, int(ttl_s))))

    def release_sweep(self, dataset_id: str) -> None:
        """Give a claimed sweep back (its task could not be published), so the next caller may sweep."""
        self._r.delete(self._key(dataset_id, "sweep"))

    # --- shards
    def start_attempt(self, dataset_id: str, index: int, max_attempts: int, running: dict[str, Any]) -> int:
        """Count one execution of a shard and note who runs it; -1 when its attempts are used up."""
        keys = [self._key(dataset_id), self._key(dataset_id, "tries"), self._key(dataset_id, "running")]
        return int(self._start(keys=keys, args=[index, repr(time.time()), json.dumps(running), max_attempts]))

    def refund_attempt(self, dataset_id: str, index: int) -> int:
        """Give back an execution that failed only because a dependency was unreachable (an outage): it no longer
        counts towards max_attempts (`attempts` still counts it). Returns the shard's outages so far."""
        with self._r.pipeline(transaction=True) as pipe:
            pipe.hincrby(self._key(dataset_id, "tries"), index, -1)
            pipe.hincrby(self._key(dataset_id, "outages"), index, 1)
            return int(pipe.execute()[1])

    def end_attempt(self, dataset_id: str, index: int) -> None:
        self._r.hdel(self._key(dataset_id, "running"), index)

    def running(self, dataset_id: str) -> dict[int, dict[str, Any]]:
        return {int(i): json.loads(v) for i, v in self._r.hgetall(self._key(dataset_id, "running")).items()}

    def live_running(self, dataset_id: str, now: float, lease_s: float) -> set[int]:
        """Shards whose current execution started less than lease_s (the hard time limit) ago."""
        return {i for i, who in self.running(dataset_id).items() if now - float(who.get("since", 0)) < lease_s}

    def pending(self, dataset_id: str, indices: list[int], now: float, lease_s: float) -> list[int]:
        """Of `indices`, the shards neither committed, nor failed, nor running within their lease."""
        if not indices:
            return []
        with self._r.pipeline(transaction=False) as pipe:
            pipe.smismember(self._key(dataset_id, "done"), indices)
            pipe.smismember(self._key(dataset_id, "failed"), indices)
            pipe.hmget(self._key(dataset_id, "running"), indices)
            done, failed, running = pipe.execute()
        out = []
        for i, d, f, who in zip(indices, done, failed, running):
            live = who is not None and now - float(json.loads(who).get("since", 0)) < lease_s
            if not (d or f or live):
                out.append(i)
        return out

    def attempts(self, dataset_id: str, index: int) -> int:
        """Executions of shard `index` started so far."""
        return int(self._r.hget(self._key(dataset_id, "tries"), index) or 0)

    def tries(self, dataset_id: str) -> dict[int, int]:
        return {int(i): int(v) for i, v in self._r.hgetall(self._key(dataset_id, "tries")).items()}

    def record_error(self, dataset_id: str, index: int, message: str) -> None:
        self._r.hset(self._key(dataset_id, "errors"), index, message[:2000])

    def last_error(self, dataset_id: str, index: int) -> str | None:
        return self._r.hget(self._key(dataset_id, "errors"), index)

    def is_committed(self, dataset_id: str, index: int) -> bool:
        return bool(self._r.sismember(self._key(dataset_id, "done"), index))

    def is_failed(self, dataset_id: str, index: int) -> bool:
        return bool(self._r.sismember(self._key(dataset_id, "failed"), index))

    def commit(self, dataset_id: str, commit: ShardCommit, touch: bool = True) -> tuple[bool, int, int]:
        """Count a committed shard once (no longer failed, if it was); return (newly added, shards done, shards
        failed). touch=False leaves touched_at as it is."""
        keys = [self._key(dataset_id), self._key(dataset_id, "done"), self._key(dataset_id, "shards"),
                self._key(dataset_id, "failed"), self._key(dataset_id, "errors"), self._key(dataset_id, "shown")]
        args = [commit.index, commit.frame_count, commit.to_json(), repr(time.time()) if touch else ""]
        added, done, failed = self._commit(keys=keys, args=args)
        return bool(added), int(done), int(failed)

    def fail(self, dataset_id: str, index: int, message: str) -> tuple[int, int]:
        """Give up on a shard (unless it was committed meanwhile); return (shards done, shards failed)."""
        keys = [self._key(dataset_id), self._key(dataset_id, "failed"), self._key(dataset_id, "errors"),
                self._key(dataset_id, "done"), self._key(dataset_id, "shown")]
        _, done, failed = self._fail(keys=keys, args=[index, message[:2000], repr(time.time()), ERRORS_SHOWN])
        return int(done), int(failed)

    def commits(self, dataset_id: str) -> list[ShardCommit]:
        """Committed shards, in shard order."""
        raw = self._r.hgetall(self._key(dataset_id, "shards"))
        return sorted((ShardCommit.from_json(v) for v in raw.values()), key=lambda c: c.index)

    def commits_between(self, dataset_id: str, start: int, stop: int) -> list[ShardCommit]:
        """Committed shards with index in [start, stop), in shard order: O(stop - start), whatever the total."""
        if stop <= start:
            return []
        raw = self._r.hmget(self._key(dataset_id, "shards"), list(range(start, stop)))
        return [ShardCommit.from_json(v) for v in raw if v is not None]

    def claim_finalise(self, dataset_id: str, ttl_s: int) -> bool:
        """True for the one caller that may finalise now; the TTL lets a later caller replace a dead one."""
        return bool(self._r.set(self._key(dataset_id, "final"), "1", nx=True, ex=ttl_s))

    def release_finalise(self, dataset_id: str) -> None:
        self._r.delete(self._key(dataset_id, "final"))

    def is_finalising(self, dataset_id: str) -> bool:
        return bool(self._r.exists(self._key(dataset_id, "final")))

    # --- single-frame answers (on a client made with decode_responses=False)
    def reply_key(self, token: str) -> str:
        return f"{self._prefix}:reply:{token}"


def raw_client(url: str, **options: Any):
    """A client of the Redis at `url` answering bytes (decode_responses=False): single-frame answers (push_reply,
    wait_reply) and the broker's messages are bytes."""
    import redis

    return redis.Redis.from_url(url, **options)


def push_reply(raw_redis, key: str, header: dict[str, Any], body: bytes, ttl_s: int) -> None:
    """Hand one frame file (or an error) to the API waiting on `key`."""
    with raw_redis.pipeline() as pipe:
        pipe.rpush(key, json.dumps(header).encode() + b"\n" + body)
        pipe.expire(key, ttl_s)
        pipe.execute()


def wait_reply(raw_redis, key: str, timeout_s: float) -> tuple[dict[str, Any], bytes] | None:
    """Block until a worker answers on `key` or the timeout passes (None)."""
    got = raw_redis.blpop([key], timeout=timeout_s)
    if got is None:
        return None
    head, _, body = got[1].partition(b"\n")
    return json.loads(head), body
