"""Tiny local datasets for the tests of what reads a finished dataset (export, preview), and the CLI to run on them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.local.generate import generate, reproduce

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
# What reads a finished dataset is under test, not the light: the water's closed form. The example's solved columns
# (four Jerlov types under random suns) made a 7-frame 48x36 dataset take 126 s on the 2-core CPU, nearly all of it
# first solves.
CLOSED_FORM = {"water.solved_column": False}


def closed_form_example(folder: Path) -> Path:
    """examples/urchins.yaml with CLOSED_FORM, written into `folder` as a spec file for the CLI and the benches."""
    spec = yaml.safe_load(EXAMPLE.read_text())
    spec["water"]["solved_column"] = False
    path = folder / "urchins.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def generate_variants(root: Path, base: dict, variants: dict[str, tuple[dict, int]]) -> dict[str, Path]:
    """One dataset per variant, name -> (spec overrides on top of `base` and CLOSED_FORM, workers), each in
    root/name."""
    made = {}
    for name, (overrides, workers) in variants.items():
        made[name] = root / name
        generate(load_spec(EXAMPLE, {**CLOSED_FORM, **base, **overrides}), made[name], workers=workers)
    return made


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def same_across_workers_and_reproduce(spec, root: Path, index: int) -> Path:
    """Generate `spec` with one worker and with two, and frame `index` again with `reproduce`; assert every file is
    the same bytes each way. Returns the one-worker dataset's folder."""
    one, two = root / "one", root / "two"
    generate(spec, one, workers=1)
    generate(spec, two, workers=2)
    assert tree(one) == tree(two)
    paths = reproduce(spec, index, root / "again")
    assert paths and all((one / p).read_bytes() == (root / "again" / p).read_bytes() for p in paths)
    return one


def seasynth(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True)
