"""Admission over HTTP: a shard must fit the task time limit by the full cost model (seasynth.service.shards.spec_shard_seconds),
and the shard_size a refusal suggests is admitted."""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator

import httpx
from isolated_stacks import api_on
from service_stack import Stack, tiny_spec
from test_service_plumbing import HEAVY

from seasynth.service.shards import shard_seconds, spec_shard_seconds
from seasynth.service.spec.dataset import parse_spec

REFUSAL = re.compile(
    r"shard_size: (\d+) frames of 640x480 at quality 'draft' \(up to 128 objects, 1024 terrain cells a side, "
    r"24 terrains, 4 of clean/range/depth/instance/coco/yolo/mcap\) are estimated at (\d+) s per shard, over the limit of (\d+) s "
    r"\(the soft task time limit, SEASYNTH_TASK_TIME_LIMIT_S\); use shard_size <= (\d+)"
)


@contextlib.contextmanager
def unserved_api(infra: Stack) -> Iterator[httpx.Client]:
    """An API whose datasets go to the queues of a code version no worker runs: admitted specs are never rendered."""
    from seasynth.api.deps import open_services

    services = open_services(infra.settings(worker_version="0.0.0-admission", key_prefix="admission"))
    try:
        with api_on(services) as client:
            yield client
    finally:
        services.raw_redis.delete("seasynth.0.0.0-admission.shards")
        services.close()


def test_a_shard_heavy_in_objects_terrain_and_outputs_is_refused_and_the_suggested_size_fits(infra: Stack):
    soft = infra.settings().task_soft_time_limit_s
    spec = tiny_spec(frames=100, shard_size=100, **HEAVY)
    # By resolution and quality alone (the old admission), the shard takes a sixth of the limit.
    assert shard_seconds(100, 640, 480, "draft") < soft / 6
    with unserved_api(infra) as client:
        r = client.post("/datasets", json=spec)
        assert r.status_code == 413, r.text
        (line,) = r.json()["errors"]
        m = REFUSAL.fullmatch(line)
        assert m, line
        size, need, limit, fits = map(int, m.groups())
        assert (size, need, limit) == (100, round(spec_shard_seconds(parse_spec(spec))), soft)
        # The largest shard_size that fits: one frame more would not.
        cost = lambda n: spec_shard_seconds(parse_spec({**spec, "shard_size": n}))  # noqa: E731
        assert cost(fits) <= soft < cost(fits + 1), (fits, cost(fits), cost(fits + 1))
        ok = client.post("/datasets", json={**spec, "shard_size": fits})
        assert ok.status_code == 202, ok.text
        assert ok.json()["shards_total"] == -(-100 // fits)


def test_a_frame_over_the_limit_by_itself_is_refused_without_a_shard_size(infra: Stack):
    soft = infra.settings().task_soft_time_limit_s
    spec = tiny_spec(frames=10, shard_size=1, **{**HEAVY, "quality": "high",
                                                        "camera": {"width": 4096, "height": 4096}})
    one = spec_shard_seconds(parse_spec(spec))
    assert one > soft
    with unserved_api(infra) as client:
        r = client.post("/datasets", json=spec)
    assert r.status_code == 413, r.text
    (line,) = r.json()["errors"]
    assert line.startswith("shard_size: 1 frames of 4096x4096 at quality 'high' ")
    assert line.endswith(f"over the limit of {soft} s (the soft task time limit, SEASYNTH_TASK_TIME_LIMIT_S); even "
                         f"one frame per shard is estimated at {one:.0f} s: lower the resolution, quality, object "
                         "counts, terrain.cells or outputs"), line
