"""What drawing an uploaded mesh's picture adds to its upload check: the check (seasynth.api.uploads.validate, the
child process that loads the mesh) with and without the picture, side by side in one run, for spheres of growing
triangle counts, and the drawing alone (seasynth.api.mesh_thumbnail.draw) in this process.

    python -m seasynth.bench.thumbnails [OUT_DIR]   # writes thumbnails.json and thumbnails.md (bench/results/cpu/thumbnails/)
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import trimesh

from seasynth.api.mesh_thumbnail import draw
from seasynth.api.uploads import format_of, validate

SUBDIVISIONS = (2, 4, 6, 7)  # icospheres of 320 to 327,680 triangles, binary STL as uploaded
REPEATS = 3


def once(run) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def seconds(run) -> float:
    return statistics.median(once(run) for _ in range(REPEATS))


def measure(work: Path) -> list[dict]:
    rows = []
    for sub in SUBDIVISIONS:
        mesh = trimesh.creation.icosphere(sub)
        path = work / f"sphere{sub}.stl"
        mesh.export(path)
        fmt, picture = format_of(path.name), work / f"sphere{sub}.png"
        # off and on alternate, so both see the machine in the same state
        off, on = [], []
        for _ in range(REPEATS):
            off.append(once(lambda p=path, f=fmt: validate(p, f, p.name)))
            on.append(once(lambda p=path, f=fmt, t=picture: validate(p, f, p.name, thumbnail=t)))
        rows.append({"triangles": len(mesh.faces), "stl_bytes": path.stat().st_size,
                     "check_s": round(statistics.median(off), 3),
                     "check_with_picture_s": round(statistics.median(on), 3),
                     "draw_s": round(seconds(lambda m=mesh: draw(m.vertices, m.faces)), 3),
                     "picture_bytes": picture.stat().st_size})
    return rows


def main(argv: list[str]) -> int:
    out = Path(argv[0]) if argv else Path("bench/results/cpu/thumbnails")
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        rows = measure(Path(work))
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    machine = f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores, {cpu}"
    (out / "thumbnails.json").write_text(json.dumps({"machine": machine, "repeats": REPEATS, "rows": rows}, indent=1))
    lines = ["# An uploaded mesh's picture: what it adds to the upload check", "",
             f"machine: {machine}  ",
             (f"command: `python -m seasynth.bench.thumbnails`; seconds are medians of {REPEATS} runs (the check without and "
              "with the picture alternating); `draw` is the drawing alone, in process"), "",
             "| triangles | STL bytes | check s | check with picture s | draw s | picture bytes |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['triangles']} | {r['stl_bytes']} | {r['check_s']} | {r['check_with_picture_s']} | {r['draw_s']} "
              f"| {r['picture_bytes']} |" for r in rows]
    (out / "thumbnails.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
