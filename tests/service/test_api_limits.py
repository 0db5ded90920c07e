"""Frame requests that wait for a frame worker cannot starve the API: their number is bounded
(SEASYNTH_MAX_FRAME_WAITS) and /healthz answers from the event loop, over real HTTP against `seasynth serve`."""

from __future__ import annotations

import base64
import json
import time
from concurrent.futures import ThreadPoolExecutor

import anyio.to_thread
import httpx
import pytest
import redis
from service_stack import Stack, tiny_spec, wait_for

from seasynth.service.queues import frame_queue, shard_queue
from seasynth.service.records.store import push_reply
from seasynth.service.settings import Settings

VERSION = "0.0.0-framewaits"  # no worker consumes its queues: frame requests wait until this test answers them
RETRY_AFTER_S = 7
PROMPT_S = 5.0  # an answer from the event loop (on a loaded 2-core machine), against the 60 s a frame may wait


def sync_route_threads() -> int:
    """The threads Starlette runs sync routes (and sync dependencies) on: anyio's default limiter."""

    async def tokens() -> float:
        return anyio.to_thread.current_default_thread_limiter().total_tokens

    return int(anyio.run(tokens))


def answer_frames(raw: redis.Redis, count: int) -> list[int]:
    """Play a frame worker: answer `count` frame tasks of VERSION's queue, each with a PNG naming its index."""
    indices = []
    for _ in range(count):
        _, message = raw.blpop([frame_queue(VERSION)], timeout=15)
        _, index, _, reply_key = json.loads(base64.b64decode(json.loads(message)["body"]))[0]
        push_reply(raw, reply_key, {"ok": True, "name": f"image_2/{index:06d}.png"}, b"\x89PNG %d" % index, ttl_s=60)
        indices.append(index)
    return indices


def test_the_default_bound_leaves_most_threads_to_other_routes():
    assert Settings.model_fields["max_frame_waits"].default <= sync_route_threads() // 4


def test_frame_requests_holding_every_thread_leave_health_answering_and_more_are_refused_at_once(infra: Stack):
    """With the bound at the thread pool's size, waiting frame requests take every thread: /healthz still answers
    at once, one frame request more gets 503 with Retry-After at once naming the limit, and answered requests
    free their places."""
    threads = sync_route_threads()
    proc, url = infra.start_api({"SEASYNTH_WORKER_VERSION": VERSION, "SEASYNTH_KEY_PREFIX": "framewaits",
                                 "SEASYNTH_MAX_FRAME_WAITS": str(threads), "SEASYNTH_FRAME_TIMEOUT_S": "60",
                                 "SEASYNTH_RETRY_AFTER_S": str(RETRY_AFTER_S)})
    raw = redis.Redis.from_url(infra.settings().redis_url)
    raw.delete(frame_queue(VERSION))
    pool = ThreadPoolExecutor(threads + 1)
    try:
        dataset_id = httpx.post(f"{url}/datasets", json=tiny_spec(frames=threads)).json()["id"]
        frame = f"{url}/datasets/{dataset_id}/frames/{{}}"
        waiting = [pool.submit(httpx.get, frame.format(i), timeout=60) for i in range(threads)]
        wait_for(lambda: raw.llen(frame_queue(VERSION)) == threads, 30, f"{threads} frame requests waiting")
        with pytest.raises(httpx.ReadTimeout):  # every thread is taken: a sync route cannot run
            httpx.get(f"{url}/datasets/{dataset_id}", timeout=0.5)

        asked = time.monotonic()
        health = httpx.get(f"{url}/healthz", timeout=PROMPT_S)
        assert health.status_code == 200 and health.json()["status"] == "ok", health.text
        refused = httpx.get(frame.format(0), timeout=PROMPT_S)
        assert time.monotonic() - asked < PROMPT_S
        assert refused.status_code == 503 and refused.headers["retry-after"] == str(RETRY_AFTER_S), refused.text
        assert refused.json()["detail"] == (
            f"{threads} frame requests are already waiting for a frame worker, the limit of this API process "
            f"(SEASYNTH_MAX_FRAME_WAITS); retry after {RETRY_AFTER_S} s")
        assert raw.llen(frame_queue(VERSION)) == threads, "the refused request must not reach a frame worker"

        assert sorted(answer_frames(raw, threads)) == list(range(threads))
        got = [f.result(30) for f in waiting]
        assert [(r.status_code, r.content) for r in got] == [(200, b"\x89PNG %d" % i) for i in range(threads)]
        again = pool.submit(httpx.get, frame.format(3), timeout=30)
        assert answer_frames(raw, 1) == [3]
        assert again.result(30).status_code == 200, "answered requests free their places"
    finally:
        proc.stop()
        pool.shutdown(cancel_futures=True)
        raw.delete(frame_queue(VERSION), shard_queue(VERSION))
        raw.close()
