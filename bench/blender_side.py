"""Blender's side of `seasynth bench blender` (bench/blender.py): builds each exported frame in bpy and renders it.

Runs in Blender's own Python environment (bpy 4.5 needs numpy < 2, seasynth numpy >= 2) as a script,
`python bench/blender_side.py SCENES OUT --engine ...`, so it imports only the standard library and numpy. The
conversions from seasynth's conventions to Blender's (camera, sun, volume) are pure functions here, tested without
bpy (tests/test_bench_blender.py).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# The paper's model (urchins.yaml's) has no surface: its sun reaches the seabed unattenuated. Blender's water box
# ends this far above the camera workspace's top, so the sun crosses as little water as the cameras allow.
SURFACE_CLEARANCE_M = 0.1
WATER_EXTENT_M = 200.0  # the water box's side: wide and deep enough that open-water rays end in water, not sky
PHASE_G = 0.92  # Henyey-Greenstein anisotropy of the water (the physical model's default)
SENSOR_WIDTH_MM = 36.0  # Blender's default; only lens / sensor width matters

@dataclass(frozen=True)
class BlenderCamera:
    """A Blender camera's settings: lens_mm over SENSOR_WIDTH_MM (horizontal fit) and shifts in units of the width."""

    lens_mm: float
    shift_x: float
    shift_y: float
    matrix_world: np.ndarray  # (4, 4) float64: Blender camera axes (x right, y up, looking down -z) to world metres


BLENDER_FROM_KITTI = np.diag([1.0, -1.0, -1.0, 1.0])  # KITTI x right, y down, z forward -> Blender x, y up, -z


def blender_camera(K: np.ndarray, width: int, height: int, world_from_cam: np.ndarray) -> BlenderCamera:
    """The Blender camera of a KITTI pinhole: K (3, 3) pixels with pixel centres at integer coordinates, the image
    width x height pixels, world_from_cam (4, 4) KITTI camera axes to world metres.

    Blender's pixel i covers [i, i + 1) with the optical axis at width / 2 - shift_x * width (and height / 2 +
    shift_y * width, rows counted down), so cx = (width - 1) / 2 - shift_x * width and cy = (height - 1) / 2 +
    shift_y * width. Square pixels only (fx == fy), as Blender's pixel aspect would also rescale the resolution.
    """
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not math.isclose(fx, fy, rel_tol=1e-9):
        raise ValueError(f"K: fx {fx} != fy {fy}; the Blender export supports square pixels only")
    return BlenderCamera(
        lens_mm=float(fx * SENSOR_WIDTH_MM / width),
        shift_x=float(((width - 1) / 2.0 - cx) / width),
        shift_y=float((cy - (height - 1) / 2.0) / width),
        matrix_world=np.asarray(world_from_cam, dtype=np.float64) @ BLENDER_FROM_KITTI,
    )


def blender_project(cam: BlenderCamera, width: int, height: int, points_world: np.ndarray) -> np.ndarray:
    """(n, 2) float64 KITTI pixel coordinates (u right, v down, centres at integers) of (n, 3) world points seen by
    a Blender camera: Blender's own pinhole (focal length in pixels lens_mm / SENSOR_WIDTH_MM * width, axis shifted)."""
    world_from_b = cam.matrix_world
    p = (np.asarray(points_world, dtype=np.float64) - world_from_b[:3, 3]) @ world_from_b[:3, :3]  # Blender cam axes
    f = cam.lens_mm / SENSOR_WIDTH_MM * width
    depth = -p[:, 2]
    x = width / 2.0 - cam.shift_x * width + f * p[:, 0] / depth  # Blender film coordinates, origin top-left corner
    y = height / 2.0 + cam.shift_y * width - f * p[:, 1] / depth
    return np.stack([x - 0.5, y - 0.5], axis=1)


def sun_matrix(sun_dir_world: np.ndarray) -> np.ndarray:
    """(4, 4) float64 rotation of a Blender sun lamp whose light travels along -sun_dir_world (a lamp shines down
    its local -z, so local +z is the unit vector towards the sun)."""
    z = np.asarray(sun_dir_world, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.99 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2] = x, np.cross(z, x), z
    return out


def volume_settings(absorption: np.ndarray, scattering: np.ndarray) -> dict[str, tuple]:
    """Blender's Volume Absorption and Volume Scatter inputs for absorption a and scattering b ((3,) 1/m, RGB).

    Blender's absorption coefficient is density * (1 - color) and its scattering coefficient density * color."""
    a = np.asarray(absorption, dtype=np.float64)
    b = np.asarray(scattering, dtype=np.float64)
    da, db = float(max(a.max(), 1e-12)), float(max(b.max(), 1e-12))
    return {"absorption": (tuple(float(c) for c in 1.0 - a / da), da),
            "scatter": (tuple(float(c) for c in b / db), db)}


def _materials(bpy):
    """The colour-attribute surface material and the water volume material, made once and reused by every frame."""
    surface = bpy.data.materials.new("albedo")
    surface.use_nodes = True
    nodes, links = surface.node_tree.nodes, surface.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_name = "albedo"
    links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    water = bpy.data.materials.new("water")
    water.use_nodes = True
    nodes, links = water.node_tree.nodes, water.node_tree.links
    nodes.remove(nodes["Principled BSDF"])
    out = nodes["Material Output"]
    absorb = nodes.new("ShaderNodeVolumeAbsorption")
    scatter = nodes.new("ShaderNodeVolumeScatter")
    add = nodes.new("ShaderNodeAddShader")
    links.new(absorb.outputs[0], add.inputs[0])
    links.new(scatter.outputs[0], add.inputs[1])
    links.new(add.outputs[0], out.inputs["Volume"])
    return surface, water


def _build_frame(bpy, data, surface, water) -> None:
    """Rebuilds the scene's objects from one exported frame (what a dataset generator does per frame)."""
    scene = bpy.context.scene
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    for coll in (bpy.data.meshes, bpy.data.cameras, bpy.data.lights):
        for block in list(coll):
            coll.remove(block)
    width, height = (int(v) for v in data["size"])
    verts, faces, albedo = data["vertices"], data["faces"], data["albedo"]
    v0 = f0 = 0
    for k, (nv, nf) in enumerate(zip(data["vertex_counts"], data["face_counts"])):
        me = bpy.data.meshes.new(f"mesh{k}")
        me.vertices.add(int(nv))
        me.vertices.foreach_set("co", verts[v0:v0 + nv].ravel())
        me.loops.add(3 * int(nf))
        me.loops.foreach_set("vertex_index", faces[f0:f0 + nf].ravel())
        me.polygons.add(int(nf))
        me.polygons.foreach_set("loop_start", np.arange(0, 3 * nf, 3, dtype=np.int32))
        me.polygons.foreach_set("use_smooth", np.ones(nf, dtype=bool))
        colour = me.color_attributes.new("albedo", "FLOAT_COLOR", "POINT")
        rgba = np.ones((nv, 4), dtype=np.float32)
        rgba[:, :3] = albedo[v0:v0 + nv]
        colour.data.foreach_set("color", rgba.ravel())
        me.update()
        me.materials.append(surface)
        scene.collection.objects.link(bpy.data.objects.new(f"mesh{k}", me))
        v0, f0 = v0 + nv, f0 + nf
    cam = blender_camera(data["K"], width, height, data["world_from_cam"])
    cd = bpy.data.cameras.new("camera")
    cd.sensor_fit, cd.sensor_width, cd.lens = "HORIZONTAL", SENSOR_WIDTH_MM, cam.lens_mm
    cd.shift_x, cd.shift_y = cam.shift_x, cam.shift_y
    cd.clip_start, cd.clip_end = 0.02, 300.0
    camera = bpy.data.objects.new("camera", cd)
    camera.matrix_world = cam.matrix_world.T.tolist()  # mathutils takes rows
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = math.pi * float(data["sun_intensity"])  # seasynth's J = albedo x irradiance; Blender's is / pi
    lamp = bpy.data.objects.new("sun", sun)
    lamp.matrix_world = sun_matrix(data["sun_dir_world"]).T.tolist()
    scene.collection.objects.link(lamp)
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (*[float(data["ambient"])] * 3, 1.0)
    if np.any(data["absorption"] > 0) or np.any(data["scattering"] > 0):
        vol = volume_settings(data["absorption"], data["scattering"])
        nodes = water.node_tree.nodes
        nodes["Volume Absorption"].inputs["Color"].default_value = (*vol["absorption"][0], 1.0)
        nodes["Volume Absorption"].inputs["Density"].default_value = vol["absorption"][1]
        nodes["Volume Scatter"].inputs["Color"].default_value = (*vol["scatter"][0], 1.0)
        nodes["Volume Scatter"].inputs["Density"].default_value = vol["scatter"][1]
        nodes["Volume Scatter"].inputs["Anisotropy"].default_value = float(data["phase_g"])
        top, side = float(data["surface_z"]), WATER_EXTENT_M
        box = bpy.data.meshes.new("water")
        corners = [(x, y, z) for x in (-side / 2, side / 2) for y in (-side / 2, side / 2) for z in (top - side, top)]
        box.from_pydata(corners, [], [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4),
                                      (1, 5, 7, 3)])
        box.materials.append(water)
        scene.collection.objects.link(bpy.data.objects.new("water", box))


def _camera_error_px(bpy, data) -> float:
    """Max pixel distance between Blender's own projection (bpy_extras) of 200 scene vertices in front of the
    camera and K's: checks blender_camera in Blender itself."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    scene = bpy.context.scene
    bpy.context.view_layer.update()
    width, height = (int(v) for v in data["size"])
    cam_from_world = np.linalg.inv(data["world_from_cam"])
    pts = data["vertices"].astype(np.float64)
    pc = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uv = pc @ np.asarray(data["K"]).T
    uv = uv[:, :2] / uv[:, 2:]
    inside = (pc[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    pick = np.flatnonzero(inside)[:: max(1, inside.sum() // 200)]
    err = 0.0
    for i in pick:
        ndc = world_to_camera_view(scene, scene.camera, Vector(pts[i].tolist()))
        u, v = ndc.x * width - 0.5, (1.0 - ndc.y) * height - 0.5
        err = max(err, math.hypot(u - uv[i, 0], v - uv[i, 1]))
    return err


def render_frames(scenes: list[Path], out: Path, engine: str, samples: int, denoise: bool, threads: int) -> dict:
    """Renders each exported scene to OUT/NNNNNN.png; seconds per frame from reading the arrays to the PNG written."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = engine
    scene.render.resolution_percentage = 100
    scene.render.threads_mode, scene.render.threads = "FIXED", threads
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "PNG", "8"
    scene.view_settings.view_transform = "Standard"  # plain sRGB, as seasynth's frames
    if engine == "CYCLES":
        scene.cycles.device = "CPU"
        scene.cycles.samples = samples
        scene.cycles.use_adaptive_sampling = False  # exactly `samples` per pixel
        scene.cycles.use_denoising = denoise
        if denoise:
            scene.cycles.denoiser = "OPENIMAGEDENOISE"
    else:
        scene.eevee.taa_render_samples = samples
    if scene.world is None:
        scene.world = bpy.data.worlds.new("world")
    scene.world.use_nodes = True
    surface, water = _materials(bpy)
    out.mkdir(parents=True, exist_ok=True)
    seconds, camera_px = [], None
    for path in scenes:
        t0 = time.perf_counter()
        with np.load(path) as f:
            data = dict(f)
        width, height = (int(v) for v in data["size"])
        scene.render.resolution_x, scene.render.resolution_y = width, height
        _build_frame(bpy, data, surface, water)
        scene.render.filepath = str(out / f"{path.stem}.png")
        bpy.ops.render.render(write_still=True)
        seconds.append(time.perf_counter() - t0)
        if camera_px is None:
            camera_px = _camera_error_px(bpy, data)
    c = scene.cycles
    info = {"blender": bpy.app.version_string, "engine": engine, "samples": samples, "denoise": denoise,
            "threads": scene.render.threads, "seconds": seconds, "camera_check_px": camera_px}
    if engine == "CYCLES":
        info["bounces"] = {"max": c.max_bounces, "diffuse": c.diffuse_bounces, "volume": c.volume_bounces}
    else:
        import gpu

        info["gpu"] = gpu.platform.renderer_get()
    return info


def _blender_main(argv: list[str]) -> None:
    p = argparse.ArgumentParser(description="Blender's side of bench/blender.py (run with bpy's Python).")
    p.add_argument("scenes", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--engine", required=True)
    p.add_argument("--samples", type=int, required=True)
    p.add_argument("--denoise", action="store_true")
    p.add_argument("--threads", type=int, required=True)
    p.add_argument("--frames", type=int, required=True, help="The first FRAMES scenes (sorted) are rendered.")
    p.add_argument("--result", type=Path, required=True)
    a = p.parse_args(argv)
    scenes = sorted(a.scenes.glob("*.npz"))[: a.frames]
    info = render_frames(scenes, a.out, a.engine, a.samples, a.denoise, a.threads)
    a.result.write_text(json.dumps(info))


if __name__ == "__main__":
    _blender_main(sys.argv[1:])
