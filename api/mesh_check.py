"""The mesh check of an upload, in a child process with a memory budget (seasynth.api.uploads runs it): a mesh whose loading
needs more than the budget fails here instead of taking the API process's memory (a 256 MiB binary STL, 5.4 M
triangles, took 3.5 GB and 49 s of CPU to load with trimesh on a 2-core machine).

    python api/mesh_check.py PATH FILE_TYPE BUDGET_MIB NAME WORKDIR

NAME is the upload's name, for messages. FILE_TYPE zip: the archive's members are checked and extracted into WORKDIR
(an empty folder the caller removes; seasynth.service.archives, as the workers extract it) and its one mesh is loaded
by path, so the files it names resolve. glb: its embedded images
are checked against the pixel budget (seasynth.service.textures) before anything decodes them.
Prints one JSON line: {"ok": true}, {"error": "NAME: ..."} (not a valid mesh) or {"memory": true} (over the budget).
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path


def check(path: str, file_type: str, name: str, work: Path) -> dict:
    if file_type in ("zip", "glb"):
        from seasynth.service.errors import AssetError

        try:
            if file_type == "zip":
                from seasynth.service.archives import safe_extract

                inner = safe_extract(Path(path), work / "asset", name=name)
                member = inner.relative_to(work / "asset").as_posix()
                return load(str(inner), inner.suffix[1:].lower(), f"{name}: member {member!r}")
            from seasynth.service.textures import check_glb

            check_glb(Path(path), name)
        except AssetError as err:
            return {"error": str(err)}
    with open(path, "rb") as f:
        return load(f, file_type, name)


def load(source, file_type: str, name: str) -> dict:
    """Load a mesh file (a path, or an open file) as the workers read it (worker/scene/assets/user.py): every part
    with triangles, transforms applied."""
    import numpy as np
    import trimesh

    try:
        scene = trimesh.load_scene(source, file_type=file_type)
        parts = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except MemoryError:
        raise
    except Exception as err:  # any parser failure means a bad file
        return {"error": f"{name}: not a valid {file_type} mesh ({type(err).__name__}: {err})"}
    if not parts:
        return {"error": f"{name}: the {file_type} mesh has no triangles"}
    if not all(np.isfinite(np.asarray(g.vertices)).all() for g in parts):
        return {"error": f"{name}: the {file_type} mesh has vertices that are NaN or infinite"}
    return {"ok": True}


def main(argv: list[str]) -> int:
    path, file_type, budget_mib, name, work = argv[0], argv[1], int(argv[2]), argv[3], Path(argv[4])
    # Run by its path, this folder is first on sys.path: its modules (errors, models, ...) must not shadow others.
    # Where the package is not installed but laid out as .../seasynth/api/ (the API image probe), its root is
    # appended, so seasynth.service imports.
    here = Path(__file__).parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != here.resolve()]
    if here.parent.name == "seasynth":
        sys.path.append(str(here.parent.parent))
    limit = budget_mib * 2**20
    resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))  # heap and private mappings: what loading allocates
    try:
        answer = check(path, file_type, name, work)
    except MemoryError:
        answer = {"memory": True}
    sys.stdout.write(json.dumps(answer) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
