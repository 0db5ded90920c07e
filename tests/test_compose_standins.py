"""The stand-ins for Docker Hub's images, without Docker: docker/standins/build.sh covers every image the compose file
and Dockerfiles name, docker/compose.standins.yml changes nothing but the build network, and the S3 stand-in
(`minio`, moto kept on disk) and its `mc` behave as the stack needs, run here as plain processes."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import boto3
import pytest
import yaml
from botocore.config import Config

ROOT = Path(__file__).resolve().parents[1]
STANDINS = ROOT / "docker" / "standins"
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_every_pulled_image_has_a_stand_in():
    """What compose pulls (services without build) is exactly what build.sh makes stand-ins of, and every
    Dockerfile starts from the python tag build.sh imports."""
    pulled = {svc["image"].rsplit(":", 1)[0] for svc in SERVICES.values() if "build" not in svc}
    script = (STANDINS / "build.sh").read_text()
    assert set(re.findall(r"compose_image (\S+)\)", script)) == pulled
    python_tag = "python:3.11-slim"
    assert re.search(r"^PYTHON_TAG=\$\(sed .*docker/api\.Dockerfile", script, re.M)
    for dockerfile in sorted((ROOT / "docker").glob("*.Dockerfile")):
        bases = re.findall(r"^FROM (\S+)", dockerfile.read_text(), re.M)
        assert bases and all(b == python_tag for b in bases), (dockerfile.name, bases)


def test_standins_override_only_builds_on_the_host_network():
    override = yaml.safe_load((ROOT / "docker" / "compose.standins.yml").read_text())
    built = {name for name, svc in SERVICES.items() if "build" in svc}
    assert set(override["services"]) == built
    assert all(svc == {"build": {"network": "host"}} for svc in override["services"].values())


def test_recovery_override_sets_the_same_limits_everywhere():
    """tests/compose.recovery.yml: the three-minute limit reaches every client of the broker (Flower included), or
    the shortest visibility timeout would win."""
    override = yaml.safe_load((ROOT / "tests" / "compose.recovery.yml").read_text())
    clients = {name for name in SERVICES if name in {"api", "reconciler", "worker", "worker-frames", "flower"}}
    assert set(override["services"]) == clients
    envs = [svc["environment"] for svc in override["services"].values()]
    assert all(e == {"SEASYNTH_TASK_TIME_LIMIT_S": "180", "SEASYNTH_STALL_TIMEOUT_S": "60"} for e in envs)


@pytest.fixture
def s3_server(tmp_path):
    """The `minio` stand-in on a free port with its data in tmp_path/data; yields a function that (re)starts it."""
    procs: list[subprocess.Popen] = []
    port = free_port()
    url = f"http://127.0.0.1:{port}"

    def start():
        p = subprocess.Popen([sys.executable, str(STANDINS / "s3" / "minio"), "server", str(tmp_path / "data"),
                              "--address", f"127.0.0.1:{port}", "--console-address", ":9001"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(p)
        s3 = boto3.client("s3", endpoint_url=url, aws_access_key_id="k", aws_secret_access_key="s",
                          region_name="us-east-1", config=Config(retries={"max_attempts": 1}))
        deadline = time.monotonic() + 30
        while True:
            try:
                s3.list_buckets()
                return p, s3
            except Exception:
                if p.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"the minio stand-in did not start (exit {p.poll()})") from None
                time.sleep(0.1)

    yield start, url
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_s3_standin_keeps_objects_across_a_restart(s3_server, tmp_path):
    """Objects written, overwritten, deleted, uploaded in parts and refused by a conditional write come back after
    a restart exactly as they were: bytes, content type, ETag (a multipart one too), last-modified."""
    start, _ = s3_server
    p, s3 = start()
    s3.create_bucket(Bucket="seasynth")
    s3.create_bucket(Bucket="gone")
    s3.delete_bucket(Bucket="gone")
    s3.put_object(Bucket="seasynth", Key="a/b.json", Body=b"{}", ContentType="application/json")
    s3.put_object(Bucket="seasynth", Key="a", Body=b"first")
    s3.put_object(Bucket="seasynth", Key="a", Body=b"second")  # a key that is also a prefix of another
    s3.put_object(Bucket="seasynth", Key="deleted", Body=b"x")
    s3.delete_object(Bucket="seasynth", Key="deleted")
    big = os.urandom(9 * 2**20)  # past boto3's 8 MiB multipart threshold
    (tmp_path / "big").write_bytes(big)
    s3.upload_file(str(tmp_path / "big"), "seasynth", "shards/000.tar")
    with pytest.raises(s3.exceptions.ClientError, match="PreconditionFailed"):
        s3.put_object(Bucket="seasynth", Key="a", Body=b"third", IfNoneMatch="*")
    before = {k: s3.head_object(Bucket="seasynth", Key=k) for k in ("a/b.json", "a", "shards/000.tar")}
    p.send_signal(signal.SIGTERM)
    assert p.wait(10) == 0

    _, s3 = start()
    assert [b["Name"] for b in s3.list_buckets()["Buckets"]] == ["seasynth"]
    keys = [o["Key"] for o in s3.list_objects_v2(Bucket="seasynth")["Contents"]]
    assert keys == ["a", "a/b.json", "shards/000.tar"]
    assert s3.get_object(Bucket="seasynth", Key="a")["Body"].read() == b"second"
    assert s3.get_object(Bucket="seasynth", Key="shards/000.tar")["Body"].read() == big
    for key, head in before.items():
        again = s3.head_object(Bucket="seasynth", Key=key)
        for field in ("ETag", "ContentType", "LastModified", "ContentLength"):
            assert again[field] == head[field], (key, field)
    assert before["shards/000.tar"]["ETag"].endswith('-2"')  # it was a multipart upload


def test_mc_standin_sets_up_the_bucket_as_compose_does(s3_server, tmp_path):
    """minio-init's command (alias set, mb --ignore-existing, twice: compose may run it again) and the health
    check's `mc ready`, which fails while the server is down."""
    start, url = s3_server
    env = {**os.environ, "HOME": str(tmp_path / "home"), "MINIO_ROOT_USER": "u", "MINIO_ROOT_PASSWORD": "p"}
    mc = [sys.executable, str(STANDINS / "s3" / "mc")]

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([*mc, *args], env=env, capture_output=True, text=True, timeout=60)

    p, s3 = start()
    assert run("alias", "set", "local", url, "u", "p").returncode == 0
    for _ in range(2):
        r = run("mb", "--ignore-existing", "local/seasynth")
        assert r.returncode == 0, r.stderr
    assert "exists" in run("mb", "local/seasynth").stderr
    assert [b["Name"] for b in s3.list_buckets()["Buckets"]] == ["seasynth"]
    assert run("ready", "local").returncode == 0
    assert "not set" in run("ready", "elsewhere").stderr
    p.kill()
    p.wait()
    r = run("ready", "local")
    assert r.returncode == 1 and "not ready" in r.stderr
