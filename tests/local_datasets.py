"""Tiny local datasets for the tests of what reads a finished dataset (export, preview), and the CLI to run on them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.local.generate import generate

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"


def generate_variants(root: Path, base: dict, variants: dict[str, tuple[dict, int]]) -> dict[str, Path]:
    """One dataset per variant, name -> (spec overrides on top of `base`, workers), each in root/name."""
    made = {}
    for name, (overrides, workers) in variants.items():
        made[name] = root / name
        generate(load_spec(EXAMPLE, {**base, **overrides}), made[name], workers=workers)
    return made


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def seasynth(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True)
