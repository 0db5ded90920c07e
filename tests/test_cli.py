"""The `seasynth` command as a user runs it: exit codes, messages on stderr, and what it leaves on disk."""

from __future__ import annotations

import json
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


# ------------------------------------------------------------------ unusable user files


def spec_file(tmp_path: Path, edit) -> Path:
    """The example spec, tiny, changed by `edit(data)`, written next to the files it names."""
    import yaml

    data = yaml.safe_load(EXAMPLE.read_text())
    data.update(frames=2, camera={**data["camera"], "width": 48, "height": 36})
    edit(data)
    path = tmp_path / "spec.json"
    path.write_text(json.dumps(data))
    return path


def test_undecodable_texture_is_refused_before_the_output_folder_is_made(tmp_path):
    (tmp_path / "seabed.png").write_bytes(b"\x89PNG\r\n\x1a\n but not really")
    spec = spec_file(tmp_path, lambda d: d["terrain"].update(texture={"path": "seabed.png"}))
    r = seasynth("generate", spec, "--out", tmp_path / "out")
    assert r.returncode == 1
    assert r.stderr.startswith(f"error: {tmp_path / 'seabed.png'}: cannot decode image") and "Traceback" not in r.stderr
    assert len(r.stderr.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_unreadable_mesh_is_refused_before_the_output_folder_is_made(tmp_path):
    (tmp_path / "urchin.ply").write_bytes(b"ply\nformat garbage\n\x00\x01\x02")
    spec = spec_file(tmp_path, lambda d: d["targets"].update(assets=[{"path": "urchin.ply"}]))
    r = seasynth("generate", spec, "--out", tmp_path / "out")
    assert r.returncode == 1
    assert r.stderr.startswith(f"error: {tmp_path / 'urchin.ply'}: cannot parse as ply") and "Traceback" not in r.stderr
    assert len(r.stderr.splitlines()) == 1
    assert not (tmp_path / "out").exists()
