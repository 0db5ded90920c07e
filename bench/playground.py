"""Playground latency: how long the page waits for a preview, over real HTTP against `seasynth playground`
(uvicorn, the in-process renderer, JSON and PNG data URLs included), per view set, plus the strip of 8 frames.

The first request of a run (renderer start, terrain and asset builds, shader compiles) is reported apart; the rest
step through frame indices, as a user does when judging a spec."""

from __future__ import annotations

import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import yaml

from seasynth.bench.throughput import machine_description
from seasynth.service.spec.dataset import read_spec_file, resolve_paths

# The first row visits each frame for the first time: it builds the terrain and asset variants the frame draws
# (cached after); later rows revisit the same frames with more views.
VIEW_SETS = {"image, first visit": [], "image": [], "image+depth+instance": ["depth", "instance"],
             "all views": ["depth", "instance", "clean", "air"]}
TARGET_MS = 300  # issue 13: a preview at 640x480 within 300 ms on the 2-core CPU


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


def run(spec_path: Path, out: Path, frames: int = 12, platform: str = "egl") -> dict:
    """Time previews of `frames` frame indices per view set and one strip; write out/playground.{json,md}."""
    spec = resolve_paths(read_spec_file(spec_path), spec_path.parent)
    spec["frames"] = max(int(spec.get("frames", 100)), frames + 8)
    port = _port()
    base = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as tmp:
        spec_file = Path(tmp) / "spec.yaml"
        spec_file.write_text(yaml.safe_dump(spec))
        proc = subprocess.Popen([sys.executable, "-m", "seasynth.cli", "playground", str(spec_file), "--no-browser",
                                 "--port", str(port), "--out", str(Path(tmp) / "runs"), "--gl", platform],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            rows, cold = _measure(base, spec, frames, proc)
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    result = {"machine": machine_description(), "spec": str(spec_path), "width": spec["camera"]["width"],
              "height": spec["camera"]["height"], "frames_per_row": frames, "cold_ms": cold, "rows": rows,
              "target_ms": TARGET_MS}
    out.mkdir(parents=True, exist_ok=True)
    (out / "playground.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "playground.md").write_text(markdown(result))
    print(markdown(result))
    return result


def _measure(base: str, spec: dict, frames: int, proc: subprocess.Popen) -> tuple[list[dict], float]:
    with httpx.Client(base_url=base, timeout=120) as client:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"seasynth playground exited: {proc.stderr.read().decode()[-2000:]}")
            try:
                if client.get("/playground/config").status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("seasynth playground did not answer within 120 s")
            time.sleep(0.2)

        def post(path: str, body: dict) -> tuple[float, dict]:
            t0 = time.perf_counter()
            r = client.post(path, json=body)
            ms = (time.perf_counter() - t0) * 1000
            r.raise_for_status()
            return ms, r.json()

        cold, _ = post("/playground/preview", {"spec": spec, "frame": 0, "views": []})
        rows = []
        for name, views in VIEW_SETS.items():
            wall, render = [], []
            for i in range(1, frames + 1):
                ms, body = post("/playground/preview", {"spec": spec, "frame": i, "views": views})
                wall.append(ms)
                render.append(body["render_ms"])
            rows.append({"what": f"preview: {name}", "p50_ms": round(statistics.median(wall), 1),
                         "p90_ms": round(_percentile(wall, 0.9), 1), "max_ms": round(max(wall), 1),
                         "render_p50_ms": round(statistics.median(render), 1)})
        strip = [post("/playground/strip", {"spec": spec, "first": 8 * k, "count": 8})[0] for k in range(3)]
        rows.append({"what": "strip of 8 (160 px wide)", "p50_ms": round(statistics.median(strip), 1),
                     "p90_ms": round(_percentile(strip, 0.9), 1), "max_ms": round(max(strip), 1),
                     "render_p50_ms": None})
    return rows, round(cold, 1)


def markdown(r: dict) -> str:
    lines = [f"# Playground latency: {r['spec']} at {r['width']}x{r['height']} (`draft`)", "",
             f"Machine: {r['machine']}. Over HTTP to `seasynth playground`; {r['frames_per_row']} frame indices per "
             f"row. First request of the run (start-up, builds): {r['cold_ms']} ms.", "",
             "| request | p50 ms | p90 ms | max ms | render p50 ms (server side) |", "|---|---|---|---|---|"]
    for row in r["rows"]:
        render = "" if row["render_p50_ms"] is None else row["render_p50_ms"]
        lines.append(f"| {row['what']} | {row['p50_ms']} | {row['p90_ms']} | {row['max_ms']} | {render} |")
    lines += ["", f"Target: a preview within {r['target_ms']} ms."]
    return "\n".join(lines) + "\n"
