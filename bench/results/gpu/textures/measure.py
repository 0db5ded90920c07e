"""What per-pixel textures (materials.procedural) cost at 1920x1080 on one GPU: whole `seasynth generate` commands
with them off and on, interleaved (off, on, off, on, ...), and the render-only ceiling (bench/gpu_ceiling.py) the
same way. Off draws the frames of the code before textures (vertex colours; the untextured path is unchanged, its
frames byte-identical), so the ratio is textures' cost against today's code, side by side in one run.

    python3 bench/results/gpu/textures/measure.py OUT [--pairs N] [--frames N] [--ceiling-pairs N]

Run from the repo root with seasynth importable. "off" is examples/urchins.yaml with `materials: {procedural: false}`
added; "on" is the example itself (textures and the far field on by default). gpu_ceiling.py takes no spec, so its
"off" runs a copy whose load_spec overrides add materials.procedural: false. Writes OUT/textures.json.
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

EXAMPLE = Path("examples/urchins.yaml")
CEILING = Path("bench/gpu_ceiling.py")
CEILING_OVERRIDES = '{"camera.width": w, "camera.height": h}'


def gpu_util_sampler(path: Path) -> subprocess.Popen | None:
    if shutil.which("nvidia-smi") is None:
        return None
    return subprocess.Popen(["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits",
                             "-lms", "250"], stdout=path.open("w"), stderr=subprocess.DEVNULL)


def mean_util(path: Path) -> float | None:
    if not path.exists():
        return None
    vals = [float(x) for x in path.read_text().split() if x.strip().replace(".", "").isdigit()]
    return round(sum(vals) / len(vals), 1) if vals else None


def generate(spec: Path, out: Path, frames: int, size: str, tmp: Path, cache: Path | None = None) -> dict:
    """One whole `generate` command; cache: its SEASYNTH_CACHE_DIR (None: the environment's)."""
    cmd = [sys.executable, "-m", "seasynth.cli", "generate", str(spec), "--out", str(out), "--frames", str(frames),
           "--width", size.split("x")[0], "--height", size.split("x")[1], "--workers", "auto"]
    subprocess.run(["rm", "-rf", str(out)], check=True)
    util = tmp / "util.txt"
    util.unlink(missing_ok=True)
    sampler = gpu_util_sampler(util)
    t = time.perf_counter()
    env = dict(os.environ) | ({} if cache is None else {"SEASYNTH_CACHE_DIR": str(cache)})
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    if sampler is not None:
        sampler.terminate()
        sampler.wait()
    tail = (p.stdout + p.stderr).strip().splitlines()[-1:] if (p.stdout + p.stderr).strip() else []
    images = len(list((out / "image_2").glob("*.png"))) if (out / "image_2").is_dir() else 0
    renderer = re.search(r" on (.+)$", p.stdout.strip().splitlines()[-1]) if p.stdout.strip() else None
    return {"command": " ".join(["python3", *cmd[1:]]), "rc": p.returncode, "wall_s": round(wall, 2),
            "frames": frames, "images_written": images, "wall_fps": round(frames / wall, 1),
            "mean_gpu_util": mean_util(util), "renderer": renderer.group(1) if renderer else None,
            "last_line": tail[0] if tail else "", "stderr_tail": p.stderr[-600:] if p.returncode else ""}


def ceiling(script: Path, size: str, arg: str) -> dict:
    cmd = [sys.executable, str(script), size, arg]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    m = re.search(r"render-only fps=\s*([0-9.]+)", p.stdout)
    return {"command": " ".join(["python3", *cmd[1:]]), "rc": p.returncode, "wall_s": round(time.perf_counter() - t, 1),
            "render_only_fps": float(m.group(1)) if m else None, "stdout": p.stdout.strip(),
            "stderr_tail": p.stderr[-600:] if p.returncode else ""}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=1200)
    ap.add_argument("--ceiling-pairs", type=int, default=2)
    ap.add_argument("--ceiling-arg", default="default@24@2")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--warmup-frames", type=int, default=96, help="One run of each, not counted, first: caches.")
    ap.add_argument("--anisotropy", type=int, default=None, help="materials.anisotropy of 'on' (default: the example's)")
    ap.add_argument("--cache", choices=["cold", "warm"], default=None,
                    help="cold: every generate starts from an empty cache folder (SEASYNTH_CACHE_DIR), as a first "
                    "run of the code; warm: one folder, filled by the warm-up runs, as every later run. Default: "
                    "the environment's")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    tmp = Path("/tmp/textures")
    tmp.mkdir(exist_ok=True)
    data = yaml.safe_load(EXAMPLE.read_text())
    specs = {"off": tmp / "urchins-textures-off.yaml", "on": EXAMPLE}
    specs["off"].write_text(yaml.safe_dump({**data, "materials": {"procedural": False}}, sort_keys=False))
    on_overrides = ""
    if a.anisotropy is not None:
        specs["on"] = tmp / f"urchins-anisotropy-{a.anisotropy}.yaml"
        specs["on"].write_text(yaml.safe_dump({**data, "materials": {"anisotropy": a.anisotropy}}, sort_keys=False))
        on_overrides = f', "materials.anisotropy": {a.anisotropy}'
        result_name = f"textures-anisotropy-{a.anisotropy}.json"
    else:
        result_name = "textures.json"
    if a.cache is not None:
        result_name = result_name.replace(".json", f"-cache-{a.cache}.json")

    def cache_for(n: int) -> Path | None:
        if a.cache is None:
            return None
        folder = tmp / ("cache-warm" if a.cache == "warm" else f"cache-cold-{n}")
        if a.cache == "cold":
            shutil.rmtree(folder, ignore_errors=True)
        return folder
    source = CEILING.read_text()
    assert source.count(CEILING_OVERRIDES) == 1, "bench/gpu_ceiling.py's load_spec overrides moved"
    scripts = {"on": tmp / "gpu_ceiling_on.py", "off": tmp / "gpu_ceiling_off.py"}
    scripts["on"].write_text(source.replace(CEILING_OVERRIDES, CEILING_OVERRIDES[:-1] + on_overrides + "}"))
    off_overrides = CEILING_OVERRIDES[:-1] + ', "materials.procedural": False}'
    scripts["off"].write_text(source.replace(CEILING_OVERRIDES, off_overrides))
    gpu = (subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                          capture_output=True, text=True).stdout.strip() if shutil.which("nvidia-smi") else "no GPU")
    result = {"machine": f"{gpu}; {os.cpu_count()} cores", "resolution": [int(x) for x in a.size.split("x")],
              "frames": a.frames, "off_spec": "examples/urchins.yaml with materials.procedural: false",
              "on_spec": "examples/urchins.yaml" + (f" with materials.anisotropy: {a.anisotropy}" if on_overrides else ""),
              "cache": a.cache, "generate": [], "ceiling": []}

    def save():
        (a.out / result_name).write_text(json.dumps(result, indent=1) + "\n")

    for mode in ("off", "on") if a.warmup_frames else ():
        w = generate(specs[mode], Path("/tmp/gw"), a.warmup_frames, a.size, tmp, cache_for(-1))
        print("warm-up (not counted):", json.dumps(w), flush=True)
    for i in range(a.pairs):
        for mode in ("off", "on"):
            n = len(result["generate"])
            r = {"mode": mode, "run": i, **generate(specs[mode], Path(f"/tmp/g{n}"), a.frames, a.size, tmp,
                                                       cache_for(n))}
            result["generate"].append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "stderr_tail"}), r["stderr_tail"], flush=True)
            save()
    for i in range(a.ceiling_pairs):
        for mode in ("off", "on"):
            r = {"mode": mode, "run": i, **ceiling(scripts[mode], a.size, a.ceiling_arg)}
            result["ceiling"].append(r)
            print(json.dumps(r), flush=True)
            save()
    for key, metric in (("generate", "wall_fps"), ("ceiling", "render_only_fps")):
        rows = result[key]
        mean = {m: [r[metric] for r in rows if r["mode"] == m and r["rc"] == 0 and r[metric]] for m in ("off", "on")}
        if all(mean.values()):
            summary = {m: round(sum(v) / len(v), 1) for m, v in mean.items()}
            result[f"{key}_mean_{metric}"] = summary
            result[f"{key}_ratio_on_to_off"] = round(summary["on"] / summary["off"], 3)
            print(key, summary, "ratio on/off", result[f"{key}_ratio_on_to_off"], flush=True)
    save()


if __name__ == "__main__":
    main()
