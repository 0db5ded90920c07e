"""What a run of tests/test_compose.py measured and which of its checks passed, written as markdown (the full run's
is committed as bench/results/compose.md)."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

CHECKS = ("non-root, healthy", "byte-identical to local generate", "both /metrics", "worker SIGKILLed mid-run",
          "Redis restarted mid-run", "Flower lists the workers", "down/up keeps datasets", "GPU worker image builds")
FULL_ONLY = {"worker SIGKILLed mid-run", "Redis restarted mid-run", "GPU worker image builds"}


def machine() -> str:
    with open("/proc/meminfo", encoding="ascii") as f:
        mem_kib = next(int(line.split()[1]) for line in f if line.startswith("MemTotal"))
    return (f"{os.cpu_count()} cores, {mem_kib / 2**20:.0f} GiB memory, {platform.system()} {platform.release()}, "
            f"{platform.freedesktop_os_release().get('PRETTY_NAME', '')}")


class Report:
    def __init__(self) -> None:
        self.timings: dict[str, float] = {}  # step -> seconds, in the order the run took them
        self.facts: dict[str, str] = {}
        self.passed: dict[str, str] = {}  # check (one of CHECKS) -> what it saw
        self.started = datetime.now(timezone.utc)
        self.t0 = time.monotonic()
        self.load_start = os.getloadavg()[0]

    def timed(self, name: str, fn: Callable[[], Any]) -> Any:
        t0 = time.monotonic()
        out = fn()
        self.timings[name] = time.monotonic() - t0
        return out

    def result(self, check: str, full: bool) -> str:
        if check in self.passed:
            return f"passed: {self.passed[check]}"
        return "not run at this size" if check in FULL_ONLY and not full else "NOT PASSED (failed or not run)"

    def write(self, path: Path, full: bool, workers: int, size: tuple[int, int]) -> None:
        how = "full size (CI's)" if full else "reduced size (SEASYNTH_COMPOSE=reduced)"
        lines = [
            "# The compose stack, built and run (tests/test_compose.py)",
            "",
            f"Run {self.started:%Y-%m-%d %H:%M} UTC at {how}.",
            f"Machine: {machine()}; load average {self.load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at "
            "the end (other test runs shared the machine).",
            f"Engine: {self.facts.get('engine', '?')} (Debian's docker.io, vfs storage, no iptables, no default "
            f"bridge), docker-compose {self.facts.get('compose', '?')}; images from docker/standins/build.sh "
            "(no Docker Hub here: deploy/README.md).",
            "Stack: docker-compose.yml + docker/compose.standins.yml + tests/compose.recovery.yml (three-minute task "
            f"limit), profile monitor, {workers} shard worker(s); datasets of examples/urchins.yaml at "
            f"{size[0]}x{size[1]}.",
            "",
            "| step | seconds |",
            "| --- | ---: |",
            *(f"| {name} | {seconds:.0f} |" for name, seconds in self.timings.items()),
            "",
            "| check | result |",
            "| --- | --- |",
            *(f"| {c} | {self.result(c, full)} |" for c in CHECKS),
            "",
            f"Processes' uids: {self.facts.get('uids', '?')}.",
            "",
        ]
        path.write_text("\n".join(lines))
