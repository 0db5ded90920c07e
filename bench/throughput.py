"""Throughput: per-stage times, steady-state seconds per frame, output configurations, and the ratio to one
stock `pyrender.OffscreenRenderer.render(scene)` call on the same scenes, all measured in one run."""

from __future__ import annotations

import json
import os
import platform as host_platform
import statistics
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec, load_spec
from seasynth.worker.scene.disk_cache import ENV

STAGES = ("sampling", "render", "formation", "ids", "labels", "encode", "write")
WARMUP = 5  # frames excluded from steady state (first uploads, shader compiles, cache fills)

# Output configurations: each row switches on one more pass (or the water off), so each cost is shown.
CONFIGS: dict[str, dict] = {
    "image only": {"outputs.labels": False, "outputs.meta": False},
    "image+labels": {},
    "+depth": {"outputs.depth": True},
    "+instance": {"outputs.depth": True, "outputs.instance": True},
    "+clean/range": {"outputs.depth": True, "outputs.instance": True, "outputs.clean": True, "outputs.range": True},
    "water off": {"water.enabled": False},
    # The seabed beyond the tile (terrain.far_field, on by default): its cost beside the tile alone.
    "far field off": {"terrain.far_field": False},
    # Per-pixel procedural textures (materials.procedural, on by default): their cost beside vertex colours.
    "textures off": {"materials.procedural": False},
    # Sensors (seasynth.worker.sensors), each on its own beside image+labels: the FLS at its defaults (256 beams x 512
    # bins, a 1454x586 render), the side-scan sonar at its defaults, then DVL+pressure.
    "+fls": {"sensors.fls.enabled": True},
    "+sss": {"sensors.sss.enabled": True},
    "+dvl+pressure": {"sensors.dvl.enabled": True, "sensors.pressure.enabled": True},
    # Marine snow (water.particles) at the water type's default density, beside image+labels.
    "+particles": {"water.particles.enabled": True},
}


def machine_description() -> str:
    import os

    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{host_platform.system()} {host_platform.machine()}, {os.cpu_count()} cores, {cpu}"


def stock_scene(session, spec: DatasetSpec, index: int):
    """The frame's scene as a stock pyrender.Scene: same meshes, poses, camera and sun."""
    import pyrender

    scene = session.scene(spec, index)
    view = session.view(spec, scene)
    ps = pyrender.Scene(ambient_light=[scene.lighting.ambient] * 3, bg_color=[0, 0, 0, 0])
    ps.add(pyrender.Mesh.from_trimesh(scene.terrain.mesh, smooth=True))
    for p in scene.objects:
        ps.add(pyrender.Mesh.from_trimesh(p.asset.mesh, smooth=True), pose=p.world_from_obj)
    K = view.K
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=view.near, zfar=view.far)
    gl_from_kitti = np.diag([1.0, -1.0, -1.0, 1.0])  # pyrender cameras look down -z with y up
    ps.add(cam, pose=scene.world_from_cam @ gl_from_kitti)
    sun = np.eye(4)
    d = -scene.lighting.sun_dir_world  # light travels away from the sun, along the light's -z
    z = -d / np.linalg.norm(d)
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.99 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    sun[:3, 0], sun[:3, 1], sun[:3, 2] = x, np.cross(z, x), z
    ps.add(pyrender.DirectionalLight(intensity=scene.lighting.sun_intensity), pose=sun)
    triangles = len(scene.terrain.mesh.faces) + sum(len(p.asset.mesh.faces) for p in scene.objects)
    return ps, triangles


def time_stock(scenes: list, spec: DatasetSpec) -> float:
    """Median seconds of one stock render() call (default flags) over the given pyrender scenes.

    Run it with no other renderer open: pyrender's delete() terminates the process's shared EGL display.
    """
    import pyrender

    renderer = pyrender.OffscreenRenderer(spec.camera.width, spec.camera.height)
    times = []
    try:
        for ps in scenes:
            renderer.render(ps)  # uploads this scene's meshes
            t = time.perf_counter()
            renderer.render(ps)
            times.append(time.perf_counter() - t)
    finally:
        renderer.delete()
    return statistics.median(times)


def time_stages(session, spec: DatasetSpec, frames: int, out: Path) -> dict[str, float]:
    """Median seconds per stage over frames WARMUP..frames-1 (GL work is waited for at each stage)."""
    from seasynth.worker.frame.function import frame_paths
    from seasynth.worker.local.folder import write_frame

    per_stage: dict[str, list[float]] = {s: [] for s in STAGES}
    for rel in frame_paths(spec, 0):
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
    for i in range(frames):
        last = [time.perf_counter()]
        got: dict[str, float] = {}

        def mark(stage: str) -> None:
            now = time.perf_counter()
            got[stage] = now - last[0]
            last[0] = now

        files = session.frame_files(spec, i, mark=mark)
        t = time.perf_counter()
        write_frame(out, files)
        got["write"] = time.perf_counter() - t
        if i >= WARMUP:
            for s in STAGES:
                per_stage[s].append(got.get(s, 0.0))
    return {s: statistics.median(v) for s, v in per_stage.items()}


def steady_generate(spec: DatasetSpec, out: Path) -> float:
    """Steady-state wall seconds per frame of a one-worker `generate` (frames after the warm-up)."""
    from seasynth.worker.local.generate import generate

    stamps: list[float] = []
    generate(spec, out, workers=1, on_frames=lambda n: stamps.append(time.perf_counter()))
    return (stamps[-1] - stamps[WARMUP - 1]) / (len(stamps) - WARMUP)


def warm_caches(session, spec: DatasetSpec, frames: int) -> None:
    """Build every terrain and asset variant the frames use, as a long run's process would have already."""
    for i in range(frames):
        session.scene(spec, i)


def with_overrides(spec: DatasetSpec, overrides: dict, frames: int) -> DatasetSpec:
    from seasynth.service.spec.dataset import apply_overrides

    return DatasetSpec.model_validate(apply_overrides(spec.model_dump(mode="json"), {**overrides, "frames": frames}))


def run(spec_path: Path, *, frames: int, width: int, height: int, out: Path | None, platform: str,
        preset: str = "default") -> dict:
    from seasynth.worker.frame.function import RenderSession

    base = load_spec(spec_path, {"camera.width": width, "camera.height": height, "quality": preset})
    spec = base.model_copy(update={"frames": frames})
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # First, as a new process meets it: every terrain and asset variant is built on first use (an empty cache
        # folder: none built by an earlier run).
        with mock.patch.dict(os.environ, {ENV: str(tmp / "cold-cache")}):
            cold = steady_generate(spec, tmp / "cold")
        with RenderSession(platform=platform) as session:
            renderer_name = session.renderer_name
            warm_caches(session, spec, frames)
            stages = time_stages(session, spec, min(frames, 20), tmp / "stages")
            stock = [stock_scene(session, spec, i) for i in range(10)]
        triangles = int(statistics.median(n for _, n in stock))
        # The ratio's two sides in two rounds of alternating order; each keeps its faster round (noise only adds).
        stock_s = per_frame = float("inf")
        for round_ in range(2):
            for side in ("stock", "generate") if round_ == 0 else ("generate", "stock"):
                if side == "stock":
                    stock_s = min(stock_s, time_stock([ps for ps, _ in stock], spec))
                else:
                    per_frame = min(per_frame, steady_generate(spec, tmp / f"generate-{round_}"))
        # Two rounds in alternating order; each configuration keeps its faster round (noise only adds time).
        configs: dict[str, float] = {}
        names = list(CONFIGS)
        for round_ in range(2):
            for name in names if round_ == 0 else names[::-1]:
                cfg = with_overrides(spec, CONFIGS[name], 20)
                t = steady_generate(cfg, tmp / f"cfg-{round_}-{names.index(name)}")
                configs[name] = min(t, configs.get(name, t))
    result = {
        "machine": machine_description(),
        "gl_renderer": renderer_name,
        "spec": str(spec_path),
        "resolution": [width, height],
        "preset": preset,
        "triangles_median": triangles,
        "stage_median_ms": {k: round(v * 1e3, 2) for k, v in stages.items()},
        "generate_ms_per_frame": round(per_frame * 1e3, 2),
        "generate_cold_ms_per_frame": round(cold * 1e3, 2),
        "generate_frames": frames,
        "stock_pyrender_render_ms": round(stock_s * 1e3, 2),
        "ratio_generate_to_stock_render": round(per_frame / stock_s, 3),
        "configs_ms_per_frame": {k: round(v * 1e3, 2) for k, v in configs.items()},
    }
    table = format_table(result)
    print(table)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "throughput.json").write_text(json.dumps(result, indent=1) + "\n")
        (out / "throughput.md").write_text(table + "\n")
    return result


def format_table(r: dict) -> str:
    lines = [
        f"# Throughput: {r['spec']} at {r['resolution'][0]}x{r['resolution'][1]}, preset {r['preset']}",
        "",
        f"machine: {r['machine']}  ",
        f"GL renderer: {r['gl_renderer']}  ",
        f"triangles per frame (median): {r['triangles_median']}",
        "",
        "| stage | median ms |",
        "|---|---|",
        *[f"| {k} | {v:.2f} |" for k, v in r["stage_median_ms"].items()],
        "",
        "| measure | ms per frame |",
        "|---|---|",
        f"| one-worker generate over {r['generate_frames']} frames, new process (variants built on first use) "
        f"| {r['generate_cold_ms_per_frame']:.2f} |",
        f"| one-worker generate over {r['generate_frames']} frames, steady state (every variant built; faster of 2 "
        f"rounds) | {r['generate_ms_per_frame']:.2f} |",
        f"| stock pyrender OffscreenRenderer.render(scene), default flags (faster of 2 rounds, alternating with the "
        f"row above) | {r['stock_pyrender_render_ms']:.2f} |",
        f"| **ratio generate / stock render** | **{r['ratio_generate_to_stock_render']:.3f}** |",
        "",
        "| outputs (one-worker generate, 20 frames, faster of 2 rounds) | ms per frame |",
        "|---|---|",
        *[f"| {k} | {v:.2f} |" for k, v in r["configs_ms_per_frame"].items()],
    ]
    return "\n".join(lines)
