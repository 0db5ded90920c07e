"""The CLI on bad specs and output folders: exit codes, messages naming the field or folder, nothing written."""

from __future__ import annotations

import subprocess
import sys

import pytest
from spec_helpers import EXAMPLE

# --- the CLI ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    """Run the CLI cases side by side (each start-up imports the worker): name -> (out, exit code, stdout, stderr)."""
    root = tmp_path_factory.mktemp("cli")
    bad_spec = root / "bad.yaml"
    bad_spec.write_text("camera:\n  width: 5000\n")
    full = root / "full"
    full.mkdir()
    (full / "keep.txt").write_text("mine")
    blocker = root / "a-file"
    blocker.write_text("")
    cases = {
        "bad_spec": ([str(bad_spec)], root / "out-bad"),
        "not_empty": ([str(EXAMPLE), "--width", "64", "--height", "48", "--frames", "1"], full),
        "unwritable": ([str(EXAMPLE), "--width", "64", "--height", "48", "--frames", "1"], blocker / "sub"),
    }
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-m", "seasynth.cli", "generate", *args, "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=root,
        )
        for name, (args, out) in cases.items()
    }
    results = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=120)
        results[name] = (cases[name][1], proc.returncode, stdout, stderr)
    return results


def test_cli_invalid_spec_exits_2_naming_the_field_and_writes_nothing(cli_runs):
    out, code, stdout, stderr = cli_runs["bad_spec"]
    assert code == 2, stderr
    assert "\ncamera.width: " in stderr
    assert stdout == ""
    assert not out.exists()


def test_cli_refuses_a_non_empty_output_folder_with_exit_1(cli_runs):
    out, code, _, stderr = cli_runs["not_empty"]
    assert code == 1, stderr
    assert stderr.startswith(f"error: {out}: folder is not empty")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    assert (out / "keep.txt").read_text() == "mine"


def test_cli_refuses_an_unwritable_output_folder_with_exit_1(cli_runs):
    out, code, _, stderr = cli_runs["unwritable"]
    assert code == 1, stderr
    assert stderr.startswith(f"error: {out}: cannot create or list the output folder")
    assert not out.exists()
