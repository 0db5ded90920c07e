"""A private Docker engine for the compose tests: dockerd with its data, exec root and socket in one temporary folder
(vfs storage, no iptables, no default bridge: what runs on these machines), and docker-compose on the project's
files against it. Everything it started is removed on exit: containers, dockerd, the folder.

    with docker_engine(Path(tempfile.mkdtemp())) as engine:
        compose = Compose(engine, "seasynth-test", ["docker-compose.yml", "docker/compose.standins.yml"])
        compose("up", "-d", "--no-build")
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
INSTALL_HINT = "bash .ci/setup installs it (apt-get install docker.io docker-compose debootstrap)"
TOOLS = ("dockerd", "docker", "docker-compose", "debootstrap", "unshare")
# vfs copies every layer whole, and each container's init and writable layers are two more whole copies of its
# image. The engine's folder peaked at 17.8 GB (16.6 GiB) with 3 shard workers (2026-11-29; the GPU image and the
# build stages removed before the containers start), each worker container 2 GB of it: 2 workers need ~15 GiB.
DISK_NEEDED_GIB = 16


class DockerUnavailable(Exception):
    """This machine cannot run containers at all (not root, or no namespaces): the reason to skip, said in full."""


class EngineError(RuntimeError):
    """A command of the engine or of compose failed; the message holds its output's end."""


def check_can_run(folder: Path) -> None:
    """DockerUnavailable where containers cannot run; EngineError naming what to install where a tool is missing or
    the disk is too small (those are failures to fix, not reasons to skip)."""
    if os.geteuid() != 0:
        raise DockerUnavailable("dockerd needs root, and this test runs as uid %d" % os.geteuid())
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if missing:
        raise EngineError(f"missing {', '.join(missing)}: {INSTALL_HINT}")
    probe = subprocess.run(["unshare", "--mount", "--uts", "--ipc", "--net", "--pid", "--fork", "true"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        raise DockerUnavailable(f"this kernel or sandbox refuses the namespaces containers need "
                                f"(unshare: {probe.stderr.strip() or probe.returncode})")
    free_gib = shutil.disk_usage(folder).free / 2**30
    if free_gib < DISK_NEEDED_GIB:
        raise EngineError(f"{folder}: {free_gib:.0f} GiB free, the images need about {DISK_NEEDED_GIB} GiB (vfs)")


@dataclass
class Engine:
    folder: Path
    env: dict[str, str]  # os.environ with DOCKER_HOST at this engine
    log: Path

    def docker(self, *args: str, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
        return run(["docker", *args], self.env, timeout, check)

    def log_tail(self, lines: int = 30) -> str:
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])


def run(argv: Sequence[str], env: dict[str, str], timeout: float, check: bool = True,
        cwd: Path = ROOT) -> subprocess.CompletedProcess:
    r = subprocess.run(list(argv), env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    if check and r.returncode != 0:
        out = (r.stdout + r.stderr).strip().splitlines()
        raise EngineError(f"{' '.join(argv)} exited {r.returncode}:\n" + "\n".join(out[-40:]))
    return r


@contextmanager
def docker_engine(folder: Path) -> Iterator[Engine]:
    """dockerd rooted in `folder` (which it removes at the end) until the block ends."""
    folder.mkdir(parents=True, exist_ok=True)
    try:
        check_can_run(folder)
    except Exception:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    sock = folder / "docker.sock"
    # COMPOSE_HTTP_TIMEOUT: docker-compose's wait on the engine, 60 s by default, under the workers' 90 s stop grace
    # period (docker-compose.yml): `down` timed out on the worker containers while other tests loaded the machine.
    env = {**os.environ, "DOCKER_HOST": f"unix://{sock}", "DOCKER_BUILDKIT": "0", "COMPOSE_DOCKER_CLI_BUILD": "0",
           "COMPOSE_HTTP_TIMEOUT": "300"}
    log = folder / "dockerd.log"
    with open(log, "wb") as out:
        daemon = subprocess.Popen(
            ["dockerd", "--storage-driver=vfs", "--iptables=false", "--ip6tables=false", "--bridge=none",
             "--data-root", str(folder / "data"), "--exec-root", str(folder / "exec"),
             "--pidfile", str(folder / "dockerd.pid"), "-H", f"unix://{sock}"],
            stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    engine = Engine(folder, env, log)
    try:
        deadline = time.monotonic() + 90
        while run(["docker", "info"], env, 30, check=False).returncode != 0:
            if daemon.poll() is not None:
                raise EngineError(f"dockerd exited {daemon.returncode}:\n{engine.log_tail()}")
            if time.monotonic() > deadline:
                raise EngineError(f"dockerd did not answer within 90 s:\n{engine.log_tail()}")
            time.sleep(0.5)
        yield engine
    finally:
        _stop(engine, daemon)


def _stop(engine: Engine, daemon: subprocess.Popen) -> None:
    if daemon.poll() is None:
        ids = run(["docker", "ps", "-aq"], engine.env, 60, check=False).stdout.split()
        if ids:
            run(["docker", "rm", "-f", "-v", *ids], engine.env, 300, check=False)
        daemon.send_signal(signal.SIGTERM)
        try:
            daemon.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(daemon.pid, signal.SIGKILL)  # dockerd and the containerd it started, nothing else
            daemon.wait(30)
    # dockerd unmounts what it mounted (network namespaces, container roots) when it stops; lazily unmount any it left.
    for mount in reversed(_mounts_under(engine.folder)):
        subprocess.run(["umount", "-l", mount], capture_output=True)
    shutil.rmtree(engine.folder, ignore_errors=True)


def _mounts_under(folder: Path) -> list[str]:
    prefix = str(folder.resolve()) + "/"
    with open("/proc/self/mounts", encoding="utf-8") as f:
        points = [line.split()[1].replace("\\040", " ") for line in f]
    return [p for p in points if p.startswith(prefix)]


class Compose:
    """docker-compose (Debian's 1.29) on the project's files, under one project name, against `engine`."""

    def __init__(self, engine: Engine, project: str, files: Sequence[str], profiles: Sequence[str] = ()):
        self.engine = engine
        self.base = ["docker-compose", "-p", project, *(a for f in files for a in ("-f", f)),
                     *(a for p in profiles for a in ("--profile", p))]
        self.project = project

    def __call__(self, *args: str, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
        return run([*self.base, *args], self.engine.env, timeout, check)

    def containers(self, service: str | None = None) -> list[dict]:
        """`docker inspect` of the project's containers (of `service`), running or not."""
        labels = [f"label=com.docker.compose.project={self.project}"]
        if service:
            labels.append(f"label=com.docker.compose.service={service}")
        ids = self.engine.docker("ps", "-aq", *(a for lab in labels for a in ("--filter", lab))).stdout.split()
        if not ids:
            return []
        return json.loads(self.engine.docker("inspect", *ids).stdout)

    def logs(self, service: str, lines: int = 40) -> str:
        return self("logs", "--no-color", "--tail", str(lines), service, check=False).stdout
