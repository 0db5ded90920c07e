"""What workers, reconcilers and the API coordinate through in Redis besides the dataset records themselves: the
reconciler's round lock, the set of manifests still to write, renderer pinning (live renderers, hand-backs), the
Redis process a recovery check last saw, and the broker's queue lengths. A mixin of Records (store.py), so that
Records stays the one door to Redis.

Keys (P = settings.key_prefix), kept as they were when workers and the API wrote them directly:
  P:manifests:pending   SET   datasets whose final state is decided and whose manifest.json is not written yet (the
                              write failed, or is under way); finalisers add and remove them, the periodic
                              reconciler nudges the ones left
  P:reconciler:round    STR   round lock of the periodic reconcilers (SET NX with a TTL under the period)
  P:renderers:{version} ZSET  renderer name -> last time a render process of a shard worker of `version` noted it
                              (epoch s)
  P:ds:{id}:deferred    HASH  shard index -> last time a worker of another renderer handed it back (epoch s)
  P:redis:run           STR   the run_id of the Redis process the last recovery check saw
                              (seasynth.service.records.recovery)
"""

from __future__ import annotations

from typing import Any


def pending_manifests_key(prefix: str) -> str:
    return f"{prefix}:manifests:pending"


def reconciler_round_key(prefix: str) -> str:
    return f"{prefix}:reconciler:round"


def renderers_key(prefix: str, version: str) -> str:
    return f"{prefix}:renderers:{version}"


def redis_run_key(prefix: str) -> str:
    return f"{prefix}:redis:run"


class Coordination:
    """Records' operations for the queue side, on Records' client (_r), prefix (_prefix), dataset keys (_key) and
    scripts (registered by Records.__init__)."""

    _r: Any
    _prefix: str
    _decide: Any
    _hand_back: Any
    _found: Any
    _update: Any

    # --- the connection
    def ping(self) -> None:
        """Raise unless Redis answers (readiness)."""
        self._r.ping()

    def close(self) -> None:
        self._r.close()

    def namespace(self) -> str:
        """This deployment among others sharing a Redis or a bucket: the key prefix and the Redis database."""
        return f"{self._prefix}.db{self._r.connection_pool.connection_kwargs.get('db', 0)}"

    # --- the broker's queues (Celery keeps a queue's waiting messages in Redis lists of its name)
    def queue_length(self, name: str) -> int:
        return int(self._r.llen(name))

    def queue_lengths_and_datasets(self, names: list[str]) -> tuple[list[int], int]:
        """The length of each list in `names` and the number of listed datasets, in one round trip."""
        with self._r.pipeline(transaction=False) as pipe:
            for name in names:
                pipe.llen(name)
            pipe.zcard(f"{self._prefix}:datasets")
            got = pipe.execute()
        return got[:-1], got[-1]

    # --- the periodic reconciler
    def claim_reconciler_round(self, ttl_ms: int, now: float) -> bool:
        """True for the one reconciler that may run a round now; the next round waits ttl_ms."""
        return bool(self._r.set(reconciler_round_key(self._prefix), str(now), nx=True, px=ttl_ms))

    # --- manifests still to write
    def pending_manifests(self) -> set[str]:
        return self._r.smembers(pending_manifests_key(self._prefix))

    def manifest_pending(self, dataset_id: str) -> bool:
        return bool(self._r.sismember(pending_manifests_key(self._prefix), dataset_id))

    def drop_pending_manifest(self, dataset_id: str) -> None:
        """The dataset's manifest is written (or the dataset is gone): nothing left to nudge."""
        self._r.srem(pending_manifests_key(self._prefix), dataset_id)

    def decide(self, dataset_id: str, state: str, now: float) -> str | None:
        """Move a complete live dataset to its final `state` in one step, with finished_at, and add it to the
        pending manifests; a final one keeps its state (a cancel came first). Returns the state after, None for no
        such dataset."""
        return self._decide(keys=[self._key(dataset_id), pending_manifests_key(self._prefix)],
                            args=[state, repr(now), dataset_id])

    # --- renderer pinning
    def note_renderer(self, version: str, renderer: str, now: float) -> None:
        """A render process of a shard worker of `version` runs `renderer` (its heartbeat)."""
        self._r.zadd(renderers_key(self._prefix, version), {renderer: now})

    def renderer_seen(self, version: str, renderer: str) -> float | None:
        """When a shard worker of `version` last noted `renderer` (epoch s); None: never."""
        seen = self._r.zscore(renderers_key(self._prefix, version), renderer)
        return None if seen is None else float(seen)

    def hand_back(self, dataset_id: str, index: int, now: float, live: bool) -> tuple[int, float | None] | None:
        """Count a worker of another renderer handing shard `index` back, mark the shard handed back and the
        dataset touched (no sweep republishes it). `live`: a worker of the pinned renderer is alive, so nothing
        waits for one. Returns (hand-backs, waiting since: the first hand-back since a live worker of the pinned
        renderer was last seen, or None while one is live); None for no such dataset."""
        got = self._hand_back(keys=[self._key(dataset_id), self._key(dataset_id, "deferred")],
                              args=[index, repr(now), "1" if live else "0"])
        if got is None:
            return None
        return int(got[0]), (float(got[1]) if got[1] else None)

    def handed_back(self, dataset_id: str, indices: list[int]) -> list[float | None]:
        """When a worker of another renderer last handed each shard of `indices` back; None: never."""
        got = self._r.hmget(self._key(dataset_id, "deferred"), indices)
        return [None if t is None else float(t) for t in got]

    def renderer_found(self, dataset_id: str, index: int) -> None:
        """A worker of the pinned renderer took shard `index`: it is no longer handed back, and the record's notice
        of waiting for one goes."""
        self._found(keys=[self._key(dataset_id), self._key(dataset_id, "deferred")], args=[index])

    def set_notice(self, dataset_id: str, notice: str) -> None:
        """Show `notice` in the record (why it does not progress); nothing for no such dataset."""
        self._update(keys=[self._key(dataset_id)], args=["notice", notice])

    # --- recovery from a Redis restart (seasynth.service.records.recovery)
    def redis_run(self) -> tuple[str, float]:
        """The Redis process: (run_id, seconds it has been up)."""
        info = self._r.info("server")
        return info["run_id"], float(info["uptime_in_seconds"])

    def seen_redis_run(self) -> str | None:
        """The run_id of the Redis process the last recovery check saw (note_redis_run); None: none yet."""
        return self._r.get(redis_run_key(self._prefix))

    def note_redis_run(self, run_id: str) -> None:
        self._r.set(redis_run_key(self._prefix), run_id)

    def clear_running(self, dataset_id: str, indices: list[int]) -> None:
        """Forget that shards `indices` run (their executions are over)."""
        self._r.hdel(self._key(dataset_id, "running"), *indices)
