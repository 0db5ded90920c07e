"""Throughput against Blender: seasynth's `generate` and Blender (bpy, Cycles and EEVEE) on the same sampled scenes.

Each frame's scene (seasynth's own sample of examples/urchins.yaml: meshes with per-vertex albedo, pinhole camera,
sun, ambient light, water) is exported to arrays (`export_frame`) and rebuilt in Blender as BlenderProc and Kubric
users build theirs: one object per mesh with a colour attribute feeding a Principled BSDF, a camera with the same
intrinsics and pose, a sun lamp, a uniform world colour for the ambient light, and the water as a box of homogeneous
volume (Volume Scatter + Volume Absorption: the frame's attenuation beta_D as its extinction, split as the water
type's absorption and scattering) up to just above the cameras.

bpy 4.5 needs numpy < 2 and seasynth numpy >= 2, so Blender runs in its own Python environment, with
bench/blender_side.py as its script (it imports only the standard library and numpy).
"""

from __future__ import annotations

import json
import statistics
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seasynth.bench.blender_side import PHASE_G, SURFACE_CLEARANCE_M, WATER_EXTENT_M

INSTALL_HINT = ("python3.11 -m venv .venv-blender && .venv-blender/bin/pip install 'bpy==4.5.*' (bpy 4.5 needs "
                "numpy<2, seasynth numpy>=2, so Blender gets its own environment; pass it with --blender-python)")
SEASYNTH_FRAMES = 25  # seasynth's generate: WARMUP frames, then 20 timed in steady state


@dataclass(frozen=True)
class Engine:
    """One Blender configuration: engine (CYCLES or BLENDER_EEVEE_NEXT), samples per pixel, denoiser on or off."""

    engine: str
    samples: int
    denoise: bool


ENGINES: dict[str, Engine] = {
    "cycles-16": Engine("CYCLES", 16, False),
    "cycles-16-oidn": Engine("CYCLES", 16, True),
    "cycles-64": Engine("CYCLES", 64, False),
    "eevee-16": Engine("BLENDER_EEVEE_NEXT", 16, False),
}


# ---- pure conversions (no bpy) ---------------------------------------------------------------------------------
def paper_volume(beta: np.ndarray, absorption: np.ndarray, scattering: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a, b), (3,) 1/m each: the paper model's attenuation beta ((3,) 1/m) as a volume's extinction a + b, split
    as the water type's own absorption and scattering ((3,) 1/m) split theirs. Its extinction then attenuates
    Blender's view rays as beta_D attenuates seasynth's (the type's beam attenuation a + b is 2 to 8 times beta,
    which leaves single-scattering Cycles frames nearly black)."""
    albedo = np.asarray(scattering, dtype=np.float64) / (np.asarray(absorption) + np.asarray(scattering))
    beta = np.asarray(beta, dtype=np.float64)
    return beta * (1.0 - albedo), beta * albedo


# The scene as the committed table measured it: the paper's water model, whose one haze a Blender volume box matches
# (export_frame also exports the physical model's medium and surface).
# The paper's model, with vertex colours (Blender's side reads each vertex's albedo, not per-pixel textures).
PAPER = {"water.model": "paper", "materials.procedural": False}


# ---- seasynth's side: the frame's scene as arrays -----------------------------------------------------------------
def export_frame(session, spec, index: int) -> dict[str, np.ndarray]:
    """Frame `index`'s scene as arrays (what Blender's side reads):

    vertices (V, 3) float32 world metres, faces (F, 3) int32 indexing each mesh's own vertices, albedo (V, 3)
    float32 linear RGB in [0, 1], vertex_counts / face_counts (M,) int64 per mesh (terrain first), K (3, 3),
    size (2,) int64 width, height, world_from_cam (4, 4) KITTI axes, sun_dir_world (3,), sun_intensity (),
    ambient (), absorption / scattering (3,) 1/m (zeros with the water off), phase_g (), surface_z () metres.
    """
    from seasynth.service.water import jerlov_absorption, jerlov_scattering

    scene = session.scene(spec, index)
    view = session.view(spec, scene)
    verts, faces, albedo, nv, nf = [], [], [], [], []
    for it in session.draw_items(scene):
        verts.append(it.world_vertices())
        faces.append(it.mesh.faces.astype(np.int32))
        albedo.append(it.shaded_albedo())
        nv.append(len(it.mesh.vertices))
        nf.append(len(it.mesh.faces))
    if scene.light is not None:  # the physical model: its own medium and surface
        m = scene.light.medium
        a, b, g, surface = m.a, m.b, m.g, m.surface_z
        lighting = scene.lighting
    elif scene.water is not None:
        a, b = paper_volume(scene.water.beta_D, jerlov_absorption(scene.water_type),
                            jerlov_scattering(scene.water_type))
        g, surface, lighting = PHASE_G, spec.workspaces.camera.max[2] + SURFACE_CLEARANCE_M, scene.lighting
    else:
        a, b, g, surface, lighting = np.zeros(3), np.zeros(3), PHASE_G, 0.0, scene.lighting
    return {
        "vertices": np.concatenate(verts).astype(np.float32), "faces": np.concatenate(faces),
        "albedo": np.concatenate(albedo).astype(np.float32),
        "vertex_counts": np.array(nv, dtype=np.int64), "face_counts": np.array(nf, dtype=np.int64),
        "K": np.asarray(view.K, dtype=np.float64), "size": np.array([view.width, view.height], dtype=np.int64),
        "world_from_cam": np.asarray(scene.world_from_cam, dtype=np.float64),
        "sun_dir_world": np.asarray(lighting.sun_dir_world, dtype=np.float64),
        "sun_intensity": np.float64(lighting.sun_intensity), "ambient": np.float64(lighting.ambient),
        "absorption": np.asarray(a, dtype=np.float64), "scattering": np.asarray(b, dtype=np.float64),
        "phase_g": np.float64(g), "surface_z": np.float64(surface),
    }


# ---- the bench ----------------------------------------------------------------------------------------------------
def check_blender(python: Path) -> str:
    """bpy's version in `python`, or a SeasynthError in one line saying how to install it."""
    from seasynth.service.errors import SeasynthError

    try:
        got = subprocess.run([str(python), "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True,
                             text=True, timeout=120)
    except OSError as err:
        raise SeasynthError(f"--blender-python {python}: {err.strerror}; install Blender's bpy: {INSTALL_HINT}") \
            from None
    if got.returncode != 0:
        last = (got.stderr.strip().splitlines() or ["no output"])[-1]
        raise SeasynthError(f"--blender-python {python} cannot import bpy ({last}); install it: {INSTALL_HINT}")
    return got.stdout.strip().splitlines()[-1]


def blender_run(python: Path, scenes: Path, out: Path, name: str, frames: int, threads: int) -> dict:
    """One configuration in a fresh Blender process; its per-frame seconds (bpy's import excluded), or the error."""
    e, result = ENGINES[name], out / f"{name}.json"
    script = Path(__file__).resolve().with_name("blender_side.py")
    cmd = [str(python), str(script), str(scenes), str(out / name), "--engine", e.engine,
           "--samples", str(e.samples), "--threads", str(threads), "--frames", str(frames), "--result", str(result)]
    got = subprocess.run(cmd + (["--denoise"] if e.denoise else []), capture_output=True, text=True)
    if got.returncode != 0 or not result.exists():
        lines = [line for line in (got.stderr + got.stdout).splitlines() if line.strip()]
        return {"error": f"exit {got.returncode}: " + " / ".join(lines[-3:])}
    return json.loads(result.read_text())


def run(spec_path: Path, *, frames: int, width: int, height: int, out: Path | None, blender_python: Path,
        engines: list[str], platform: str = "egl") -> dict:
    """Exports `frames` scenes of the spec, times seasynth's generate and each Blender configuration on them, and
    writes OUT/blender.{json,md,png} (or prints the table when out is None)."""
    import os
    import tempfile

    from seasynth.bench.accuracy import write_results
    from seasynth.bench.throughput import WARMUP, machine_description, steady_generate, warm_caches
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import RenderSession

    version = check_blender(blender_python)
    spec = load_spec(spec_path, {"camera.width": width, "camera.height": height, "quality": "default",
                                 "frames": max(SEASYNTH_FRAMES, frames), **PAPER})
    threads = os.cpu_count() or 1
    load = {"before": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # First as a new process meets it (every terrain and asset variant built on first use), then warm, as a
        # long run's workers are and as Blender's side is (it reads finished meshes).
        cold = steady_generate(spec, tmp / "generate-cold")
        session = RenderSession(platform=platform)  # scenes and draw items only: no GL is opened
        warm_caches(session, spec, spec.frames)
        scenes = tmp / "scenes"
        scenes.mkdir()
        triangles = []
        for i in range(frames):
            data = export_frame(session, spec, i)
            triangles.append(int(data["face_counts"].sum()))
            np.savez(scenes / f"{i:06d}.npz", **data)
        per_frame = steady_generate(spec, tmp / "generate")
        detail = (f"1 worker, preset default, image+labels+meta; frames {WARMUP}..{spec.frames - 1} after {WARMUP} "
                  f"warm-up frames")
        rows = [{"renderer": "seasynth generate", "frames": spec.frames - WARMUP, "s_per_frame": per_frame,
                 "first_s": None, "detail": f"{detail}; every asset variant built (steady state)"},
                {"renderer": "seasynth generate, new process", "frames": spec.frames - WARMUP, "s_per_frame": cold,
                 "first_s": None, "detail": f"{detail}; variants built on first use"}]
        blender = {}
        for name in engines:
            info = blender_run(blender_python, scenes, tmp / "blender", name, frames, threads)
            blender[name] = info
            print(json.dumps({name: info}), flush=True)
            if "error" in info:
                rows.append({"renderer": name, "error": info["error"]})
                continue
            s = info["seconds"]
            rows.append({"renderer": name, "frames": len(s), "first_s": s[0],
                         "s_per_frame": statistics.median(s[1:] or s), "detail": _detail(ENGINES[name], info)})
        load["after"] = os.getloadavg()[0]
        cycles = [n for n in engines if ENGINES[n].engine == "CYCLES" and "error" not in blender[n]]
        shown = max(cycles, key=lambda n: ENGINES[n].samples, default=None)  # the cleanest Cycles frame
        pics = (tmp / "generate" / "image_2" / "000000.png", tmp / "blender" / str(shown) / "000000.png")
        result = {
            "machine": machine_description(), "load_1min": {k: round(v, 2) for k, v in load.items()},
            "spec": str(spec_path), "resolution": [width, height], "blender": version, "threads": threads,
            "triangles_median": int(statistics.median(triangles)), "water": _water_note(),
            "rows": [_rounded(r, per_frame) for r in rows], "blender_runs": blender,
        }
        if out is not None:
            write_results(out, "blender", result, format_table(result), lambda path: picture(pics, shown, path))
        else:
            print(format_table(result))
    return result


def _detail(e: Engine, info: dict) -> str:
    if e.engine == "CYCLES":
        b = info["bounces"]
        return (f"Cycles CPU, {e.samples} spp, adaptive sampling off, denoiser "
                f"{'OpenImageDenoise' if e.denoise else 'off'}, {info['threads']} threads, bounces max {b['max']} / "
                f"diffuse {b['diffuse']} / volume {b['volume']}")
    return f"EEVEE (Next), {e.samples} samples, GPU: {info.get('gpu', '?')}"


def _water_note() -> str:
    return (f"seasynth: the paper's water model (the bench sets water.model: paper). Blender: a {WATER_EXTENT_M:g} m box of "
            f"homogeneous volume up to {SURFACE_CLEARANCE_M:g} m above the camera workspace, Volume Absorption + "
            f"Volume Scatter (HG g {PHASE_G}): extinction the frame's beta_D, split into absorption and scattering as "
            f"its Jerlov type's a and b")


def _rounded(row: dict, seasynth_s: float) -> dict:
    if "error" in row:
        return row
    out = dict(row, s_per_frame=round(row["s_per_frame"], 4))
    out["first_s"] = None if row["first_s"] is None else round(row["first_s"], 3)
    out["ratio_to_seasynth"] = round(row["s_per_frame"] / seasynth_s, 1)
    return out


def format_table(r: dict) -> str:
    lines = [
        f"# Throughput against Blender: {r['spec']} at {r['resolution'][0]}x{r['resolution'][1]}",
        "",
        f"machine: {r['machine']}  ",
        f"1-minute load average: {r['load_1min']['before']} before the run, {r['load_1min']['after']} after it (this "
        f"bench's own busy threads included)  ",
        f"Blender: bpy {r['blender']} (PyPI), its own process per row; CPU threads: {r['threads']}  ",
        f"triangles per frame (median): {r['triangles_median']}  ",
        f"water: {r['water']}  ",
        "Blender's seconds per frame: reading the frame's arrays, rebuilding its objects, rendering, writing the PNG "
        "(bpy's import excluded; the materials made once); the median of the frames after the first",
        "",
        "| renderer | frames | s per frame | first frame s | x seasynth's time | settings |",
        "|---|---|---|---|---|---|",
    ]
    for row in r["rows"]:
        if "error" in row:
            lines.append(f"| {row['renderer']} | not run | | | | {row['error']} |")
            continue
        first = "" if row["first_s"] is None else f"{row['first_s']:.2f}"
        lines.append(f"| {row['renderer']} | {row['frames']} | {row['s_per_frame']:.3f} | {first} | "
                     f"{row['ratio_to_seasynth']:g} | {row['detail']} |")
    return "\n".join(lines)


def picture(paths: tuple[Path, Path], shown: str | None, path: Path) -> None:
    """Frame 0: seasynth | Blender's configuration `shown`, side by side (nothing when no Cycles row ran)."""
    from PIL import Image, ImageDraw

    if shown is None:
        return
    a, b = (Image.open(p).convert("RGB") for p in paths)
    sheet = Image.new("RGB", (a.width + b.width, max(a.height, b.height) + 14), "white")
    e = ENGINES[shown]
    ImageDraw.Draw(sheet).text((2, 1), f"frame 0: seasynth (preset default) | Blender {shown} ({e.samples} spp)",
                               fill="black")
    sheet.paste(a, (0, 14))
    sheet.paste(b, (a.width, 14))
    sheet.save(path)
