"""What a scale run measures while it goes: CPU and GPU utilisation, and the rates of its finished frames."""

from __future__ import annotations

import math
import shutil
import statistics
import subprocess
import threading
from pathlib import Path

STEADY_AFTER = 0.25  # steady_fps counts frames finished after this share of the run's frames
DONE_AT_PERCENT = (10, 25, 50, 75, 90, 100)  # done_at_s: seconds until this share (%) of the frames was done


def cpu_times() -> tuple[float, float]:
    """(busy, total) jiffies of all cores from /proc/stat."""
    fields = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)  # idle + iowait
    return sum(fields) - idle, sum(fields)


class GpuSampler:
    """Mean GPU utilisation (%) from nvidia-smi every `period` seconds while running; None without nvidia-smi."""

    def __init__(self, period: float = 0.5) -> None:
        self.period, self.samples = period, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self.available = shutil.which("nvidia-smi") is not None

    def _loop(self) -> None:
        while not self._stop.wait(self.period):
            try:
                out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"],
                                     capture_output=True, text=True, timeout=5).stdout.split()
                self.samples.append(statistics.mean(float(x) for x in out))
            except (OSError, ValueError, subprocess.TimeoutExpired, statistics.StatisticsError):
                pass

    def __enter__(self) -> GpuSampler:
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self.available:
            self._thread.join()

    def mean(self) -> float | None:
        return round(statistics.mean(self.samples), 1) if self.samples else None


class CpuMeter:
    """Mean utilisation (%) of all cores between enter and exit, from /proc/stat."""

    def __enter__(self) -> CpuMeter:
        self._start = cpu_times()
        return self

    def __exit__(self, *exc: object) -> None:
        (b0, t0), (b1, t1) = self._start, cpu_times()
        self.util = round(100.0 * (b1 - b0) / max(t1 - t0, 1e-9), 1)


def rates(stamps: list[float], t0: float, wall: float) -> dict:
    """first_frame_s, wall_s, wall_fps, steady_fps and done_at_s (seconds until each DONE_AT_PERCENT share of the
    frames) of a run that started at t0, took `wall` seconds and finished a frame at each of `stamps` (several frames
    may share one stamp)."""
    # With no time between the quarter mark and the end, the steady rate is the whole run's.
    k = int(len(stamps) * STEADY_AFTER)
    span = stamps[-1] - stamps[k - 1] if 0 < k < len(stamps) else 0.0
    steady = (len(stamps) - k) / span if span > 0 else len(stamps) / wall
    # When each share of the frames was done: where a run's wall time goes (its start, its middle, its tail).
    done_at = {str(q): round(stamps[max(math.ceil(len(stamps) * q / 100) - 1, 0)] - t0, 2)
               for q in DONE_AT_PERCENT} if stamps else {}
    return {"wall_s": round(wall, 2), "first_frame_s": round(stamps[0] - t0, 2) if stamps else None,
            "wall_fps": round(len(stamps) / wall, 2), "steady_fps": round(steady, 2), "done_at_s": done_at}
