"""Every example's files, byte for byte: the hashes in tests/data/examples.sha256.json were recorded by the
command a user runs (`seasynth generate examples/NAME.yaml --out DIR`), so a change that moves code and must not
change a frame is held to it. A change meant to alter frames records new hashes (and a new version):

    python -m tests.test_examples_bytes --write
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HASHES = ROOT / "tests" / "data" / "examples.sha256.json"
EXAMPLES = sorted(p.stem for p in (ROOT / "examples").glob("*.yaml"))
SEASYNTH = Path(sys.executable).with_name("seasynth")  # the console script users run, beside this interpreter


def generate(name: str, out: Path) -> dict[str, str]:
    """sha256 of every file `seasynth generate` writes for example `name`, keyed by path relative to `out`."""
    run = subprocess.run([str(SEASYNTH), "generate", str(ROOT / "examples" / f"{name}.yaml"), "--out", str(out)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return {str(p.relative_to(out)): hashlib.sha256(located(p)).hexdigest()
            for p in sorted(out.rglob("*")) if p.is_file()}


def located(path: Path) -> bytes:
    """A file's bytes; the dataset record of an example that names the checkout's own files (its assets, made
    absolute as the spec file is loaded) with those paths written as <repo> and without its spec digest, which
    digests them: the same bytes wherever the repo is checked out."""
    data = path.read_bytes()
    if path.name != "seasynth.json" or str(ROOT).encode() not in data:
        return data
    record = json.loads(data)
    record.pop("spec_sha256")
    return json.dumps(record, sort_keys=True).replace(str(ROOT), "<repo>").encode()


def renderer_of(out: Path) -> str:
    return json.loads((out / "seasynth.json").read_text())["renderer"]


def test_every_example_has_recorded_hashes():
    assert sorted(json.loads(HASHES.read_text())["examples"]) == EXAMPLES


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_files_are_byte_identical_to_the_recorded_ones(name, tmp_path):
    recorded = json.loads(HASHES.read_text())
    files = generate(name, tmp_path)
    if renderer_of(tmp_path) != recorded["renderer"]:
        pytest.skip(f"hashes were recorded with {recorded['renderer']!r}, this GL is {renderer_of(tmp_path)!r}")
    want = recorded["examples"][name]
    assert sorted(files) == sorted(want)
    changed = [path for path in want if files[path] != want[path]]
    assert changed == []


if __name__ == "__main__":
    import tempfile

    if sys.argv[1:] != ["--write"]:
        sys.exit(f"usage: python -m tests.test_examples_bytes --write  (records {HASHES.relative_to(ROOT)})")
    with tempfile.TemporaryDirectory() as tmp:
        table = {name: generate(name, Path(tmp) / name) for name in EXAMPLES}
        renderer = renderer_of(Path(tmp) / EXAMPLES[0])
    HASHES.write_text(json.dumps({"renderer": renderer, "examples": table}, indent=1, sort_keys=True) + "\n")
    print(f"{sum(map(len, table.values()))} files of {len(table)} examples recorded in {HASHES}")
