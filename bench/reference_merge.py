"""Merge path-traced references rendered apart (on several GPUs, hosts or days) into one per scene.

    python -m seasynth.bench.reference_merge OUT IN [IN ...]

Every NAME.ref.npz found in the IN folders is merged (seasynth.bench.reference.merge: same scene digest and lamp housing,
distinct seed bases, halves weighted by their samples) into OUT/NAME.ref.npz. OUT may be one of the INs: a stored
reference grows in place. Needs numpy (and the standard library) only.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from seasynth.bench.reference import REF_SUFFIX, Reference, load_reference, merge, save_reference
from seasynth.service.errors import OutputError
from seasynth.service.files import atomic_path


def merge_folders(out: Path, folders: list[Path]) -> dict[str, Reference]:
    """The merged reference of each name found in `folders` (in the order given, files sorted by name), written
    to `out`. Raises ValueError naming the file that cannot be merged (nothing is written then), OutputError naming
    a file that cannot be written."""
    merged: dict[str, Reference] = {}
    for folder in folders:
        if not folder.is_dir():
            raise ValueError(f"{folder}: not a folder")
        for path in sorted(folder.glob(f"*{REF_SUFFIX}")):
            name = path.name[: -len(REF_SUFFIX)]
            ref = load_reference(path)
            try:
                merged[name] = merge(merged[name], ref) if name in merged else ref
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from None
    out.mkdir(parents=True, exist_ok=True)
    for name, ref in merged.items():  # each file whole, or not at all (seasynth.service.files: stdlib only)
        with atomic_path(out / f"{name}{REF_SUFFIX}") as tmp, open(tmp, "wb") as f:
            save_reference(ref, f)
    return merged


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Merge NAME.ref.npz files of several folders into OUT/NAME.ref.npz.")
    p.add_argument("out", type=Path)
    p.add_argument("inputs", type=Path, nargs="+")
    args = p.parse_args(argv)
    try:
        merged = merge_folders(args.out, args.inputs)
    except (ValueError, OutputError) as exc:
        raise SystemExit(str(exc)) from None
    for name, ref in merged.items():
        print(json.dumps({"config": name, "spp": ref.spp, "seconds": round(ref.seconds, 1),
                          "seed_bases": list(ref.seed_bases), "host": ref.host}), flush=True)


if __name__ == "__main__":
    main()
