"""The `seasynth` command as a user runs it: exit codes, messages on stderr, and what it leaves on disk."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from seasynth import service
from seasynth.worker.local.folder import RECORD

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"


def seasynth(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


# ------------------------------------------------------------------ usage errors


@pytest.mark.parametrize(
    ("args", "usage", "error"),
    [
        ((), "Usage: seasynth [OPTIONS] COMMAND", "Error: Missing command."),
        (("generate", EXAMPLE, "--out", "OUT", "--workers", "0"), "Usage: ", "Error: Invalid value for '--workers'"),
        (("generate", EXAMPLE, "--out", "OUT", "--workers", "many"), "Usage: ",
         "Error: Invalid value for '--workers'"),
        (("generate", EXAMPLE, "--out", "OUT", "--bogus"), "Usage: ", "Error: No such option: --bogus"),
        (("generate", EXAMPLE), "Usage: ", "Error: Missing option '--out'"),
        (("reproduce", EXAMPLE, "--out", "OUT"), "Usage: ", "Error: Missing option '--frame'"),
        (("bench", "throughput", "--preset", "ultra", "--out", "OUT"), "Usage: ",
         "Invalid value for '--preset': 'ultra': give one of draft, fast, default, high"),
    ],
    ids=["no-args", "workers-0", "workers-word", "unknown-option", "missing-out", "missing-frame",
         "throughput-preset"],
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


def test_a_timeline_that_cannot_be_written_is_refused_before_the_output_folder_is_made(tmp_path):
    r = seasynth("generate", EXAMPLE, "--out", tmp_path / "out", "--workers", "2", "--frames", "2",
                 "--timeline", tmp_path / "no-such-folder" / "t.jsonl")
    assert r.returncode == 1, r.stderr
    assert r.stderr.startswith(f"error: {tmp_path / 'no-such-folder' / 't.jsonl'}: cannot write the timeline")
    assert "Traceback" not in r.stderr and not (tmp_path / "out").exists()


def test_unreadable_mesh_is_refused_before_the_output_folder_is_made(tmp_path):
    (tmp_path / "urchin.ply").write_bytes(b"ply\nformat garbage\n\x00\x01\x02")
    spec = spec_file(tmp_path, lambda d: d["targets"].update(assets=[{"path": "urchin.ply"}]))
    r = seasynth("generate", spec, "--out", tmp_path / "out")
    assert r.returncode == 1
    assert r.stderr.startswith(f"error: {tmp_path / 'urchin.ply'}: cannot parse as ply") and "Traceback" not in r.stderr
    assert len(r.stderr.splitlines()) == 1
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ --resume refuses another dataset's folder


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def edit_record(out: Path, **changes) -> dict:
    """Change the dataset record as a run would have written it (same layout); keys set to None are removed."""
    record = json.loads((out / RECORD).read_text())
    record.update(state="incomplete", **changes)
    record = {k: v for k, v in record.items() if v is not None}
    (out / RECORD).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    return record


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> tuple[Path, Path, str]:
    """(folder with a user mesh and a spec naming it, a complete 2-frame dataset of it, the renderer it reported)."""
    import trimesh

    root = tmp_path_factory.mktemp("made")
    trimesh.creation.box(extents=(0.2, 0.2, 0.1)).export(root / "urchin.ply")
    spec = spec_file(root, lambda d: d["targets"].update(assets=[{"path": "urchin.ply"}]))
    out = root / "ds"
    r = seasynth("generate", spec, "--out", out)
    assert r.returncode == 0, r.stderr
    renderer = r.stdout.strip().splitlines()[-1].rsplit(" on ", 1)[1]
    return spec, out, renderer


def copy_of(made, tmp_path) -> Path:
    import shutil

    return Path(shutil.copytree(made[1], tmp_path / "ds"))


def test_record_pins_code_version_renderer_and_user_files(made):
    spec, out, renderer = made
    record = json.loads((out / RECORD).read_text())
    sha = hashlib.sha256((spec.parent / "urchin.ply").read_bytes()).hexdigest()
    assert record["state"] == "complete" and record["code_version"] == service.__version__
    assert record["renderer"] == renderer and renderer.strip()
    assert record["user_files"] == {"targets.assets.0": sha}


def test_resume_refuses_another_code_version(made, tmp_path):
    out = copy_of(made, tmp_path)
    edit_record(out, code_version="0.0.1")
    before = tree(out)
    r = seasynth("generate", made[0], "--out", out, "--resume")
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert "code version 0.0.1" in r.stderr and service.__version__ in r.stderr and "--overwrite" in r.stderr
    assert tree(out) == before


@pytest.mark.parametrize("workers", [1, 2])
def test_resume_refuses_another_renderer_before_writing_a_frame(made, tmp_path, workers):
    out = copy_of(made, tmp_path)
    for rel in ("image_2/000001.png", "label_2/000000.txt"):  # two frames to render
        (out / rel).unlink()
    edit_record(out, renderer="OtherGL 1.0")
    before = tree(out)
    r = seasynth("generate", made[0], "--out", out, "--resume", "--workers", str(workers))
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert "'OtherGL 1.0'" in r.stderr and repr(made[2]) in r.stderr and "--overwrite" in r.stderr
    assert tree(out) == before


def test_resume_refuses_a_changed_user_file(tmp_path):
    import trimesh

    mesh = tmp_path / "urchin.ply"
    trimesh.creation.box(extents=(0.2, 0.2, 0.1)).export(mesh)
    spec = spec_file(tmp_path, lambda d: d["targets"].update(assets=[{"path": "urchin.ply"}]))
    out = tmp_path / "ds"
    assert seasynth("generate", spec, "--out", out).returncode == 0
    trimesh.creation.box(extents=(0.3, 0.2, 0.1)).export(mesh)  # same path (so the same spec), other content
    edit_record(out)
    before = tree(out)
    r = seasynth("generate", spec, "--out", out, "--resume")
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert f"targets.assets.0 ({mesh})" in r.stderr and "--overwrite" in r.stderr
    assert tree(out) == before


def test_resume_of_a_record_without_renderer_or_files_completes_identically(made, tmp_path):
    out = copy_of(made, tmp_path)
    (out / "image_2/000001.png").unlink()
    edit_record(out, renderer=None, user_files=None)  # as written before the record pinned them
    r = seasynth("generate", made[0], "--out", out, "--resume")
    assert r.returncode == 0, r.stderr
    assert tree(out) == tree(made[1])


def test_generate_with_workers_auto_writes_the_same_files_as_one_worker(tmp_path):
    spec = spec_file(tmp_path, lambda data: data.update(frames=3))
    one, auto = tmp_path / "one", tmp_path / "auto"
    assert seasynth("generate", spec, "--out", one, "--workers", "1").returncode == 0
    r = seasynth("generate", spec, "--out", auto, "--workers", "auto")
    assert r.returncode == 0, r.stderr
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file() and p.name != "seasynth.json")
    assert len(files) >= 9
    assert all((one / f).read_bytes() == (auto / f).read_bytes() for f in files)


def test_a_command_whose_extra_is_missing_says_which_extra_to_install(tmp_path):
    """`seasynth playground` after `bash .ci/setup local` (the worker's packages only): one line naming the missing
    package and the extra that has it, exit 1, no traceback."""
    blocker = tmp_path / "fastapi"
    blocker.mkdir()
    (blocker / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'fastapi'\", name='fastapi')\n")
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "playground", "--no-browser"], capture_output=True,
                       text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert r.returncode == 1, r.stderr
    assert r.stderr == ("error: this command needs the Python package 'fastapi', which is not installed (the 'api' "
                        "extra: pip install -c constraints.txt -e '.[api]', or bash .ci/setup for all)\n")
