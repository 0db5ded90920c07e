"""The import root: each top-level code folder present installs as seasynth.FOLDER (the images copy only the folders
they run, so the package list is read off the tree, not written out)."""

from pathlib import Path

from setuptools import find_packages, setup

ROOTS = ("service", "worker", "api", "bench", "cli")
present = [root for root in ROOTS if (Path(__file__).parent / root / "__init__.py").is_file()]
setup(
    packages=[f"seasynth.{name}" for name in find_packages(include=[f"{root}*" for root in present])],
    package_dir={f"seasynth.{root}": root for root in present},
)
