"""The mesh check of an upload, in a child process with a memory budget (seasynth.api.uploads runs it): a mesh whose loading
needs more than the budget fails here instead of taking the API process's memory (a 256 MiB binary STL, 5.4 M
triangles, took 3.5 GB and 49 s of CPU to load with trimesh on a 2-core machine).

    python api/mesh_check.py PATH FILE_TYPE BUDGET_MIB NAME WORKDIR [THUMBNAIL]

NAME is the upload's name, for messages. FILE_TYPE zip: the archive's members are checked and extracted into WORKDIR
(an empty folder the caller removes; seasynth.service.archives, as the workers extract it) and its one mesh is loaded
by path, so the files it names resolve. glb: its embedded images
are checked against the pixel budget (seasynth.service.textures) before anything decodes them.
With THUMBNAIL, a valid mesh's picture (seasynth.api.mesh_thumbnail) is written there as PNG; where drawing it fails,
the mesh is still valid and the answer says why: {"ok": true, "thumbnail_error": "..."}.
Prints one JSON line: {"ok": true}, {"error": "NAME: ..."} (not a valid mesh) or {"memory": true} (over the budget).
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path

Y_UP = ("glb", "gltf")  # glTF is +y up; the workers turn it +z up (worker/scene/assets/user.py), so does the picture


def check(path: str, file_type: str, name: str, work: Path, thumbnail: Path | None = None) -> dict:
    answer, parts, loaded_as = _check(path, file_type, name, work)
    if parts and thumbnail is not None:
        try:
            _draw(parts, loaded_as, thumbnail)
        except Exception as err:  # noqa: BLE001 (MemoryError too: the mesh is valid, its picture is not drawn)
            answer["thumbnail_error"] = f"{type(err).__name__}: {err}"
    return answer


def _draw(parts: list, file_type: str, out: Path) -> None:
    import numpy as np

    from seasynth.api.mesh_thumbnail import png

    vertices = np.concatenate([np.asarray(g.vertices, dtype=np.float64) for g in parts])
    offsets = np.cumsum([0] + [len(g.vertices) for g in parts[:-1]])
    faces = np.concatenate([np.asarray(g.faces, dtype=np.int64) + o for g, o in zip(parts, offsets)])
    if file_type in Y_UP:
        vertices = np.column_stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]])
    out.write_bytes(png(vertices, faces))


def _check(path: str, file_type: str, name: str, work: Path) -> tuple[dict, list, str]:
    """The answer, the mesh's parts when valid, and the format they were loaded as (an archive's member's)."""
    if file_type in ("zip", "glb"):
        from seasynth.service.errors import AssetError

        try:
            if file_type == "zip":
                from seasynth.service.archives import safe_extract

                inner = safe_extract(Path(path), work / "asset", name=name)
                member, inner_type = inner.relative_to(work / "asset").as_posix(), inner.suffix[1:].lower()
                return (*load(str(inner), inner_type, f"{name}: member {member!r}"), inner_type)
            from seasynth.service.textures import check_glb

            check_glb(Path(path), name)
        except AssetError as err:
            return {"error": str(err)}, [], file_type
    with open(path, "rb") as f:
        return (*load(f, file_type, name), file_type)


def load(source, file_type: str, name: str) -> tuple[dict, list]:
    """Load a mesh file (a path, or an open file) as the workers read it (worker/scene/assets/user.py): every part
    with triangles, transforms applied. Returns the answer, and the parts when they are valid."""
    import numpy as np
    import trimesh

    try:
        scene = trimesh.load_scene(source, file_type=file_type)
        parts = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except MemoryError:
        raise
    except Exception as err:  # any parser failure means a bad file
        return {"error": f"{name}: not a valid {file_type} mesh ({type(err).__name__}: {err})"}, []
    if not parts:
        return {"error": f"{name}: the {file_type} mesh has no triangles"}, []
    if not all(np.isfinite(np.asarray(g.vertices)).all() for g in parts):
        return {"error": f"{name}: the {file_type} mesh has vertices that are NaN or infinite"}, []
    return {"ok": True}, parts


def main(argv: list[str]) -> int:
    path, file_type, budget_mib, name, work = argv[0], argv[1], int(argv[2]), argv[3], Path(argv[4])
    thumbnail = Path(argv[5]) if len(argv) > 5 else None
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
        answer = check(path, file_type, name, work, thumbnail)
    except MemoryError:
        answer = {"memory": True}
    sys.stdout.write(json.dumps(answer) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
