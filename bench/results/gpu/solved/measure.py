"""What the solved water column (the default from 0.11.0) costs at 1920x1080 on one GPU: whole `seasynth generate`
commands of examples/urchins.yaml with `water.solved_column` off and on, interleaved (off, on, off, on, ...), after
one warm-up run of each that fills the cache folder (the columns are solved once per water and code version; a
later run reads them), and the render-only ceiling (bench/gpu_ceiling.py) the same way. Also times one cold solve
of every column the example's frames take (each from an empty cache folder).

    python3 bench/results/gpu/solved/measure.py OUT [--pairs N] [--frames N] [--ceiling-pairs N]

Run from the repo root with seasynth importable; reuses bench/results/gpu/textures/measure.py's runners. Writes
OUT/solved.json.
"""

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("textures_measure", HERE.parent / "textures" / "measure.py")
runners = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(runners)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--frames", type=int, default=1200)
    ap.add_argument("--ceiling-pairs", type=int, default=1)
    ap.add_argument("--ceiling-arg", default="default@24@2")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--warmup-frames", type=int, default=96)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    tmp = Path("/tmp/solved")
    tmp.mkdir(exist_ok=True)
    data = yaml.safe_load(runners.EXAMPLE.read_text())
    specs = {"off": tmp / "urchins-solved-off.yaml", "on": runners.EXAMPLE}
    specs["off"].write_text(yaml.safe_dump({**data, "water": {**data.get("water", {}), "solved_column": False}},
                                           sort_keys=False))
    source = runners.CEILING.read_text()
    assert source.count(runners.CEILING_OVERRIDES) == 1, "bench/gpu_ceiling.py's load_spec overrides moved"
    scripts = {"on": runners.CEILING, "off": tmp / "gpu_ceiling_off.py"}
    scripts["off"].write_text(source.replace(runners.CEILING_OVERRIDES, runners.CEILING_OVERRIDES[:-1]
                                             + ', "water.solved_column": False}'))
    gpu = (subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                          capture_output=True, text=True).stdout.strip() if shutil.which("nvidia-smi") else "no GPU")
    cache = tmp / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    result = {"machine": f"{gpu}; {os.cpu_count()} cores", "resolution": [int(x) for x in a.size.split("x")],
              "frames": a.frames, "off_spec": "examples/urchins.yaml with water.solved_column: false",
              "on_spec": "examples/urchins.yaml", "generate": [], "ceiling": [], "warmup": []}

    def save():
        (a.out / "solved.json").write_text(json.dumps(result, indent=1) + "\n")

    for mode in ("off", "on"):  # the first fills the cache folder: "on" solves its columns here, timed
        w = runners.generate(specs[mode], Path("/tmp/gw"), a.warmup_frames, a.size, tmp, cache)
        result["warmup"].append({"mode": mode, **w})
        print("warm-up:", json.dumps(w), flush=True)
        save()
    for i in range(a.pairs):
        for mode in ("off", "on"):
            n = len(result["generate"])
            r = {"mode": mode, "run": i, **runners.generate(specs[mode], Path(f"/tmp/g{n}"), a.frames, a.size, tmp,
                                                            cache)}
            result["generate"].append(r)
            print(json.dumps(r), flush=True)
            save()
    os.environ["SEASYNTH_CACHE_DIR"] = str(cache)
    for i in range(a.ceiling_pairs):
        for mode in ("off", "on"):
            r = {"mode": mode, "run": i, **runners.ceiling(scripts[mode], a.size, a.ceiling_arg)}
            result["ceiling"].append(r)
            print(json.dumps(r), flush=True)
            save()
    for key, rows in (("generate", result["generate"]), ("ceiling", result["ceiling"])):
        field = "wall_fps" if key == "generate" else "render_only_fps"
        on = [r[field] for r in rows if r["mode"] == "on" and r[field]]
        off = [r[field] for r in rows if r["mode"] == "off" and r[field]]
        if on and off:
            result[f"{key}_on_over_off"] = round(sum(on) / len(on) / (sum(off) / len(off)), 3)
    save()


if __name__ == "__main__":
    main()
