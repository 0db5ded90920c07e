"""The `seasynth` command as a user runs it: exit codes, messages on stderr, and what it leaves on disk."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"


def seasynth(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


# ------------------------------------------------------------------ usage errors


@pytest.mark.parametrize(
    ("args", "usage", "error"),
    [
        ((), "Usage: seasynth [OPTIONS] COMMAND", "Error: Missing command."),
        (("generate", EXAMPLE, "--out", "OUT", "--workers", "0"), "Usage: ", "Error: Invalid value for '--workers'"),
        (("generate", EXAMPLE, "--out", "OUT", "--bogus"), "Usage: ", "Error: No such option: --bogus"),
        (("generate", EXAMPLE), "Usage: ", "Error: Missing option '--out'"),
        (("reproduce", EXAMPLE, "--out", "OUT"), "Usage: ", "Error: Missing option '--frame'"),
    ],
    ids=["no-args", "workers-0", "unknown-option", "missing-out", "missing-frame"],
)
def test_usage_errors_exit_2_with_usage_and_no_traceback(tmp_path, args, usage, error):
    r = seasynth(*args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith(usage) and error in r.stderr
    assert "Traceback" not in r.stderr
    # With no arguments typer's help goes to stdout as well; every other usage error writes nothing there.
    assert ("generate" in r.stdout and "reproduce" in r.stdout) if not args else r.stdout == ""
    assert list(tmp_path.iterdir()) == []  # nothing created (OUT is relative to tmp_path)
