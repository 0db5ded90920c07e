"""Prometheus metrics against the real stack (redis-server, moto's S3, `seasynth serve`, `seasynth worker`): the
worker's exporter sums its pool processes and counts exactly the shards and frames of a finished dataset, the API
times requests by route template, and the queue depth it reports is what Redis holds."""

from __future__ import annotations

import httpx
import pytest
from isolated_stacks import isolated
from prometheus_client.parser import text_string_to_metric_families
from service_stack import Stack, free_port, tiny_spec, wait_for, wait_state, wait_worker_ready

from seasynth.api.metrics import queue_lists
from seasynth.service import __version__
from seasynth.service.queues import frame_queue, shard_queue

KEY = "k-metrics"
IDLE_VERSION = "0.0.0-metrics"  # no worker consumes its queues: what the API publishes stays there


def samples(text: str) -> dict[tuple[str, frozenset], float]:
    """(sample name, labels) -> value of a Prometheus text exposition."""
    return {(s.name, frozenset(s.labels.items())): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def value(got: dict, name: str, **labels: str) -> float | None:
    return got.get((name, frozenset(labels.items())))


def scrape(url: str, **headers: str) -> dict:
    r = httpx.get(f"{url}/metrics", headers=headers, timeout=10)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain; version=")
    return samples(r.text)


def test_queue_depth_is_what_redis_holds_and_metrics_need_the_key(infra: Stack):
    with isolated(infra, 6, worker_version=IDLE_VERSION, api_keys=KEY) as (env, services):
        api, url = infra.start_api(env)
        try:
            assert httpx.get(f"{url}/metrics").status_code == 401  # behind the key unless SEASYNTH_METRICS_PUBLIC
            shards, frames = shard_queue(IDLE_VERSION), frame_queue(IDLE_VERSION)
            before = scrape(url, **{"X-API-Key": KEY})
            assert value(before, "seasynth_queue_messages", queue=shards, kind="shards") == 0
            assert value(before, "seasynth_queue_messages", queue=frames, kind="frames") == 0
            assert value(before, "seasynth_datasets") == 0
            for _ in range(3):
                r = httpx.post(f"{url}/datasets", json=tiny_spec(), headers={"X-API-Key": KEY})
                assert r.status_code == 202, r.text
            raw = services.raw_redis
            raw.lpush(queue_lists(shards)[-1], b"a message of priority 9")  # kombu keeps those in a list of its own
            got = scrape(url, **{"Authorization": f"Bearer {KEY}"})
            held = sum(raw.llen(name) for name in queue_lists(shards))
            assert held == 4 and raw.llen(shards) == 3  # one planner message per dataset, plus the one above
            assert value(got, "seasynth_queue_messages", queue=shards, kind="shards") == held
            assert value(got, "seasynth_queue_messages", queue=frames, kind="frames") == 0
            assert value(got, "seasynth_datasets") == 3
            # The /metrics scrape itself and each POST are timed by route template.
            assert value(got, "seasynth_api_request_seconds_count", route="/datasets", method="POST",
                         status="202") == 3
            assert value(got, "seasynth_api_request_seconds_count", route="/metrics", method="GET",
                         status="401") == 1
        finally:
            api.stop()
        public, url = infra.start_api({**env, "SEASYNTH_METRICS_PUBLIC": "true"})
        try:
            assert value(scrape(url), "seasynth_datasets") == 3  # no key needed now
            assert httpx.get(f"{url}/datasets").status_code == 401  # and every other route still needs it
        finally:
            public.stop()


def test_finished_dataset_counts_exactly_its_shards_and_frames(infra: Stack):
    """A worker of two pool processes: the exporter in its main process sums both processes' counters."""
    port = free_port()
    with isolated(infra, 6, api_keys=KEY) as (env, services):
        worker = infra.seasynth("worker-metrics", "worker", "--concurrency", "2", "--loglevel", "INFO",
                                env={**env, "SEASYNTH_WORKER_METRICS_PORT": str(port)})
        api, url = infra.start_api(env)
        try:
            wait_worker_ready(worker, 2)
            headers = {"X-API-Key": KEY}
            with httpx.Client(base_url=url, headers=headers, timeout=30) as client:
                r = client.post("/datasets", json=tiny_spec(frames=6, shard_size=2))
                assert r.status_code == 202, r.text
                dataset_id = r.json()["id"]
                reads = 0

                def finished() -> bool:
                    nonlocal reads
                    reads += 1
                    return client.get(f"/datasets/{dataset_id}").json()["state"] == "succeeded"

                wait_for(finished, 120, "the dataset to succeed", interval=0.2)
                assert httpx.get(f"{url}/datasets/{dataset_id}").status_code == 401  # no key
                assert client.get("/no/such/route").status_code == 404
            worker_url = f"http://127.0.0.1:{port}"
            # The last shard's counters move just after its commit made the dataset succeed.
            def three_counted() -> dict | None:
                m = scrape(worker_url)
                return m if value(m, "seasynth_worker_shards_total", outcome="committed") == 3 else None

            got = wait_for(three_counted, 30, "the third committed shard to be counted")
            assert value(got, "seasynth_worker_shards_total", outcome="committed") == 3
            assert value(got, "seasynth_worker_frames_total", outcome="committed") == 6
            assert value(got, "seasynth_worker_frames_total", outcome="failed") is None  # never counted
            assert value(got, "seasynth_worker_shards_total", outcome="failed") is None
            assert value(got, "seasynth_worker_frame_render_seconds_count") == 6
            assert value(got, "seasynth_worker_upload_seconds_count", kind="file") == 3  # one tar per shard
            # One commit marker per shard, and the manifest the finaliser writes.
            assert value(got, "seasynth_worker_upload_seconds_count", kind="bytes") == 4

            api_got = scrape(url, **headers)
            count = "seasynth_api_request_seconds_count"
            assert value(api_got, count, route="/datasets", method="POST", status="202") == 1
            assert value(api_got, count, route="/datasets/{id}", method="GET", status="200") == reads
            assert value(api_got, count, route="/datasets/{id}", method="GET", status="401") == 1
            assert value(api_got, count, route="<unmatched>", method="GET", status="404") == 1
            assert value(api_got, "seasynth_queue_messages", queue=shard_queue(__version__), kind="shards") == 0
        finally:
            api.stop()
            worker.stop()


def test_failed_shards_count_their_frames(infra: Stack):
    """Every shard fails its one attempt (its asset's bytes were replaced in the bucket after the dataset was
    accepted, so the worker's sha256 check refuses them): 3 shards and 6 frames counted failed, none committed."""
    from seasynth.service.shards import asset_key

    port = free_port()
    with isolated(infra, 6, api_keys=KEY, max_attempts=1) as (env, services):
        api, url = infra.start_api(env)
        worker = None
        try:
            with httpx.Client(base_url=url, headers={"X-API-Key": KEY}, timeout=30) as client:
                # Bytes of this test's own (assets are stored by content, and this one is then overwritten).
                mesh = b"# test_failed_shards_count_their_frames\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
                asset_id = client.post("/assets", files={"file": ("m.obj", mesh)}).json()["asset_id"]
                spec = tiny_spec(frames=6, shard_size=2, targets={"count": [1, 1], "assets": [{"asset_id": asset_id}]})
                r = client.post("/datasets", json=spec)
                assert r.status_code == 202, r.text
                services.store.put_bytes(asset_key(asset_id), mesh + b"# not the uploaded bytes\n")
                worker = infra.seasynth("worker-metrics-fail", "worker", "--concurrency", "1",
                                        env={**env, "SEASYNTH_WORKER_METRICS_PORT": str(port)})
                assert wait_state(client, r.json()["id"], {"failed"}, timeout=120)["shards_failed"] == 3

            def three_counted() -> dict | None:
                m = scrape(f"http://127.0.0.1:{port}")
                return m if value(m, "seasynth_worker_shards_total", outcome="failed") == 3 else None

            got = wait_for(three_counted, 30, "the third failed shard to be counted")
            assert value(got, "seasynth_worker_frames_total", outcome="failed") == 6
            assert value(got, "seasynth_worker_shards_total", outcome="committed") is None
            assert value(got, "seasynth_worker_frames_total", outcome="committed") is None
        finally:
            api.stop()
            if worker is not None:
                worker.stop()


@pytest.mark.parametrize("folder", [False, True])
def test_the_exporter_empties_a_given_folder_and_needs_the_variable_first(tmp_path, folder):
    """Counts of an earlier run in a given folder are not summed in; a fresh folder is removed afterwards."""
    import subprocess
    import sys

    given = tmp_path / "m"
    given.mkdir()
    (given / "counter_1.db").write_bytes(b"stale")
    code = (
        "import os, sys\n"
        "from pathlib import Path\n"
        "from seasynth.service.settings import Settings\n"
        "from seasynth.worker.queue.metrics import exporter\n"
        f"s = Settings(worker_metrics_port={free_port()}, worker_metrics_dir={str(given) if folder else None!r})\n"
        "with exporter(s):\n"
        "    d = Path(os.environ['PROMETHEUS_MULTIPROC_DIR'])\n"
        "    print(sorted(p.name for p in d.iterdir()), d == Path(sys.argv[1]))\n"
        "print(d.exists())\n"
    )
    run = subprocess.run([sys.executable, "-c", code, str(given)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split("\n")[:2] == (["[] True", "True"] if folder else ["[] False", "False"])
    early = subprocess.run([sys.executable, "-c", "import prometheus_client\n" + code, str(given)],
                           capture_output=True, text=True, timeout=60)
    assert early.returncode == 1 and "imported before the worker set PROMETHEUS_MULTIPROC_DIR" in early.stderr
