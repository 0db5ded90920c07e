"""Container health probe for the seasynth images (stdlib only, no curl in the slim base).

    python healthcheck.py http URL      -> exit 0 if GET URL answers 2xx within the timeout
    python healthcheck.py worker [PID]  -> exit 0 if PID (default 1, the worker's main process)
                                           is alive and has at least one child (the prefork pool)
"""

from __future__ import annotations

import os
import sys
import urllib.error
import urllib.request

TIMEOUT_S = 4.0


def check_http(url: str) -> str | None:
    """Return None when `url` answers 2xx, else the reason."""
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as resp:  # noqa: S310 (fixed local URL)
            if 200 <= resp.status < 300:
                return None
            return f"{url} answered {resp.status}"
    except (urllib.error.URLError, OSError) as exc:
        return f"{url} unreachable: {exc}"


def _ppid(stat_path: str) -> int | None:
    try:
        with open(stat_path, encoding="ascii", errors="replace") as f:
            stat = f.read()
    except OSError:  # the process ended while we looked
        return None
    # The comm field (2nd) may hold spaces and parentheses: split after the last ')'.
    return int(stat[stat.rindex(")") + 2 :].split()[1])


def check_worker(pid: int, proc: str = "/proc") -> str | None:
    """Return None when `pid` runs and has a child process (Celery's pool), else the reason."""
    if not os.path.exists(f"{proc}/{pid}/stat"):
        return f"process {pid} is gone"
    for entry in os.listdir(proc):
        if entry.isdigit() and _ppid(f"{proc}/{entry}/stat") == pid:
            return None
    return f"process {pid} has no pool processes"


def main(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "http":
        problem = check_http(argv[1])
    elif argv and argv[0] == "worker":
        problem = check_worker(int(argv[1]) if len(argv) > 1 else 1)
    else:
        print(__doc__, file=sys.stderr)
        return 2
    if problem:
        print(f"unhealthy: {problem}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
