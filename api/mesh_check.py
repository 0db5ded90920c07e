"""The mesh check of an upload, in a child process with a memory budget (seasynth.api.uploads runs it): a mesh whose loading
needs more than the budget fails here instead of taking the API process's memory (a 256 MiB binary STL, 5.4 M
triangles, took 3.5 GB and 49 s of CPU to load with trimesh on a 2-core machine).

    python api/mesh_check.py PATH FILE_TYPE BUDGET_MIB

Prints one JSON line: {"ok": true}, {"error": "..."} (not a valid mesh) or {"memory": true} (over the budget).
"""

from __future__ import annotations

import json
import resource
import sys


def check(path: str, file_type: str) -> dict:
    import numpy as np
    import trimesh

    try:
        with open(path, "rb") as f:
            # As the workers read it (worker/scene/assets/user.py): every part with triangles, transforms applied.
            scene = trimesh.load_scene(file_obj=f, file_type=file_type)
            parts = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except MemoryError:
        raise
    except Exception as err:  # any parser failure means a bad file
        return {"error": f"not a valid {file_type} mesh ({type(err).__name__}: {err})"}
    if not parts:
        return {"error": f"the {file_type} mesh has no triangles"}
    if not all(np.isfinite(np.asarray(g.vertices)).all() for g in parts):
        return {"error": f"the {file_type} mesh has vertices that are NaN or infinite"}
    return {"ok": True}


def main(argv: list[str]) -> int:
    path, file_type, budget_mib = argv[0], argv[1], int(argv[2])
    limit = budget_mib * 2**20
    resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))  # heap and private mappings: what loading allocates
    try:
        answer = check(path, file_type)
    except MemoryError:
        answer = {"memory": True}
    sys.stdout.write(json.dumps(answer) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
