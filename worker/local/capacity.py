"""How many render processes fill this machine: `generate --workers auto` and `seasynth worker --concurrency auto`.

A render process alternates CPU stages (sampling the scene, labels, encoding) with waits for its GPU (the frame's
passes and reads), so on a GPU more processes than cores keep both busy: on a 16-core H100 host, 24 processes
rendered more frames a second than 16 in every side-by-side bench row, and 32 beat 24 in one row of four
(bench/results/gpu/workers.md). More processes take longer to start, so a short run may not earn them back: as
whole 3000-frame commands, 24 against 16 gave 1.04x at 1080p and 0.95x at 720p there. On a software renderer the
rendering is CPU work itself: one process a core.

Cores are the ones this process may run on (its affinity), fewer where a cgroup's CPU quota allows less (a
container with `--cpus`, a Kubernetes CPU limit).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

from seasynth.service.gpus import GpuChoice
from seasynth.worker.render.devices import resolve_gpus

PROCESSES_PER_CORE_ON_GPU = 1.5


def usable_cores(cgroup_root: Path = Path("/sys/fs/cgroup")) -> int:
    """CPU cores this process may use: its affinity, capped by a cgroup v2 (cpu.max) or v1 (cpu.cfs_quota_us)
    quota, rounded up; at least 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    quota = _cgroup_quota(cgroup_root)
    if quota is not None:
        cores = min(cores, math.ceil(quota))
    return max(1, cores)


def _cgroup_quota(root: Path) -> float | None:
    """CPUs a cgroup quota allows (quota / period), None where there is none or it cannot be read."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]  # v2: "max 100000" or "200000 100000"
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us = int((root / "cpu" / "cpu.cfs_quota_us").read_text())  # v1: -1 when unlimited
        period_us = int((root / "cpu" / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota_us / period_us if quota_us > 0 and period_us > 0 else None


def render_processes(gpus: int, cores: int | None = None) -> int:
    """Processes that fill `cores` (default: usable_cores) rendering on `gpus` GPUs (0: a software renderer).
    On GPUs, PROCESSES_PER_CORE_ON_GPU a core, rounded up to a multiple of the GPU count so that each GPU (process
    k on GPU k mod G) gets as many."""
    cores = usable_cores() if cores is None else cores
    if gpus <= 0:
        return max(1, cores)
    n = math.ceil(cores * PROCESSES_PER_CORE_ON_GPU)
    return max(gpus, math.ceil(n / gpus) * gpus)


def gpus_found(platform: str, choice: GpuChoice | None) -> int:
    """How many GPUs render processes with this platform and GPU choice render on: the devices `choice` names, or
    (None or auto) the GPUs EGL lists here; 0 on a CPU platform, where EGL lists none, or where listing fails (the
    render processes then say why). Lists EGL's devices in this process: call it where no GL context is to be forked
    (the local generate's fork server is another process)."""
    if not platform.startswith("egl"):
        return 0
    if ":" in platform:  # egl:N, one device named
        return 1
    try:
        return len(resolve_gpus(choice or GpuChoice(), "egl"))
    except Exception:  # no EGL library, no device, more GPUs asked for than found
        return 0


def gpus_found_in_child(platform: str, choice: GpuChoice | None, timeout_s: float = 60.0) -> int:
    """gpus_found, asked in a child process: for a process that forks render processes itself (a Celery worker's
    prefork pool), which must not load a GL driver first. 0 where the child fails."""
    code = ("import sys; from seasynth.service.gpus import parse_gpus; from seasynth.worker.local.capacity import gpus_found; "
            "print(gpus_found(sys.argv[1], parse_gpus(sys.argv[2]) if sys.argv[2] else None))")
    try:
        out = subprocess.run([sys.executable, "-c", code, platform, "" if choice is None else str(choice)],
                             capture_output=True, text=True, timeout=timeout_s, check=True).stdout
        return int(out.strip().splitlines()[-1])
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return 0
