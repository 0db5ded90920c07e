"""Many exported path-tracer scenes in one file, each array stored once: configurations of one frame share their
geometry (the water and light differ), so a bundle of them is about one scene's size, small enough to send to a
render host.

    python -m seasynth.bench.reference_bundle pack DIR FILE      # DIR/*.scene.npz -> FILE
    python -m seasynth.bench.reference_bundle unpack FILE DIR    # FILE -> DIR/*.scene.npz, the same arrays

Needs only numpy.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

SCENE_SUFFIX = ".scene.npz"


def _blob_id(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.sha256(f"{a.dtype.str}:{a.shape};".encode() + a.tobytes()).hexdigest()


def pack(folder: Path, file: Path) -> dict[str, dict[str, str]]:
    """Writes every FOLDER/NAME.scene.npz into `file`; returns the manifest (scene -> array name -> blob id)."""
    manifest: dict[str, dict[str, str]] = {}
    blobs: dict[str, np.ndarray] = {}
    for path in sorted(folder.glob(f"*{SCENE_SUFFIX}")):
        with np.load(path) as z:
            names = {}
            for key in z.files:
                a = z[key]
                names[key] = _blob_id(a)
                blobs.setdefault(names[key], a)
        manifest[path.name[: -len(SCENE_SUFFIX)]] = names
    if not manifest:
        raise SystemExit(f"{folder}: no *{SCENE_SUFFIX} to pack")
    np.savez_compressed(file, manifest=np.asarray(json.dumps(manifest, sort_keys=True)), **blobs)
    return manifest


def unpack(file: Path, folder: Path) -> list[Path]:
    """Writes each scene of the bundle `file` to FOLDER/NAME.scene.npz; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    with np.load(file) as z:
        manifest = json.loads(str(z["manifest"]))
        for name, names in manifest.items():
            arrays = {key: z[blob] for key, blob in names.items()}
            for key, blob in names.items():
                if _blob_id(arrays[key]) != blob:
                    raise SystemExit(f"{file}: array {key} of {name} is damaged")
            paths.append(folder / f"{name}{SCENE_SUFFIX}")
            np.savez_compressed(paths[-1], **arrays)
    return paths


def main(argv: list[str]) -> None:
    if len(argv) != 3 or argv[0] not in ("pack", "unpack"):
        raise SystemExit(__doc__)
    if argv[0] == "pack":
        manifest = pack(Path(argv[1]), Path(argv[2]))
        print(f"{len(manifest)} scenes -> {argv[2]}")
    else:
        for path in unpack(Path(argv[1]), Path(argv[2])):
            print(path)


if __name__ == "__main__":
    main(sys.argv[1:])
