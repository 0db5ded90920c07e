"""`seasynth reconcile --every SECONDS`: the periodic reconciler, run with the command line compose and Kubernetes
give it, against real Redis and the S3 server."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml
from isolated_stacks import isolated, queued_tasks, record_only
from service_stack import Stack, tiny_spec, wait_for

from seasynth.service import __version__
from seasynth.service.queues import TASK_RECONCILE, shard_queue

ROOT = Path(__file__).resolve().parents[2]


def deployed_reconciler() -> tuple[list[str], str]:
    """(argv, liveness file) of compose's reconciler service; Kubernetes' Deployment must run the same argv."""
    svc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]["reconciler"]
    k8s = yaml.safe_load((ROOT / "deploy" / "core" / "reconciler.yaml").read_text())
    (container,) = k8s["spec"]["template"]["spec"]["containers"]
    assert container["args"] == svc["command"]
    check = svc["healthcheck"]["test"][-1]
    return svc["command"], check.split("getmtime('")[1].split("'")[0]


def test_the_deployed_reconciler_command_runs_rounds_and_stops_on_sigterm(infra: Stack, tmp_path):
    argv, alive_path = deployed_reconciler()
    assert argv[:3] == ["seasynth", "reconcile", "--every"]
    with isolated(infra, 9) as (env, services):
        stalled = record_only(services, tiny_spec(), age_s=10_000)
        fresh = record_only(services, tiny_spec())
        # alive_file() is in the temp folder: /tmp in the containers, tmp_path here.
        alive = tmp_path / Path(alive_path).name
        proc = infra.seasynth("reconciler", *argv[1:], env={**env, "TMPDIR": str(tmp_path)})
        try:
            wait_for(lambda: alive.exists() and "publish again" in proc.log.read_text(), 30, "the first round")
        finally:
            proc.stop()  # SIGTERM, in the middle of the wait for the next round
        assert proc.popen.returncode == 0, proc.tail()
        assert proc.tail().splitlines() == [
            f"reconciler: a round every {float(argv[3]):g} s",
            f"{stalled}: pending shards sent to a worker to publish again",
            "reconciler: stopped",
        ]
        sent = queued_tasks(services.raw_redis, shard_queue(__version__))
        assert sent == [(TASK_RECONCILE, [stalled, True])], (sent, fresh)


def test_reconcile_every_refuses_bad_periods_and_named_datasets(infra: Stack):
    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "seasynth.cli", "reconcile", *args], env=infra.env,
                              capture_output=True, text=True, timeout=60)

    for every in ["0", "-1", "0.01", "1e12", "inf", "nan"]:
        r = run("--every", every)
        assert r.returncode == 2 and "Invalid value for '--every': must be a number of seconds from 0.1 to 86400" \
            in r.stderr, (every, r.stderr)
    r = run("--every", "60", "a" * 32)
    assert r.returncode == 2 and "--every and DATASET_IDs exclude each other" in r.stderr, r.stderr
    assert r.stdout == ""
