"""Physics reference: renders a plain underwater scene description with Mitsuba 3's volumetric path tracer (CPU).

Conventions shared with our rasteriser: a Lambertian surface of albedo rho under irradiance E has radiance rho*E/pi;
the water is one homogeneous medium (sigma_t = sigma_a + sigma_s, Henyey-Greenstein phase) filling a large box whose
top face is the flat surface. The air-water interface is index-matched (a null boundary): its refraction is folded
into `sun_dir_world`, `sun_irradiance_rgb` and the sky's Snell-window cone by the caller.

Spot lamps use Mitsuba's `spot` profile (src/emitters/spot.cpp), with theta the angle off the lamp axis:
    I(theta) = intensity_rgb * f(theta),  f = 1 for theta <= beam_width,
    f = (cutoff - theta) / (cutoff - beam_width) for beam_width < theta < cutoff, f = 0 for theta >= cutoff.
"""

from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass

import numpy as np

VARIANT = "llvm_ad_rgb"
LLVM_ENV = "DRJIT_LIBLLVM_PATH"
LLVM_MIN_MAJOR = 16  # Dr.Jit crashes on LLVM 15 (instruction selection) and refuses 14
LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)
BOX_MIN_HALF_M = 200.0  # the water box reaches at least this far horizontally from the camera
BOX_DEPTH_M = 2000.0
NEAR_CLIP_M = 1e-3
# One Mitsuba call renders all its samples in one wavefront: ~0.3 GB of state per 2**25 samples.
MAX_SAMPLES_PER_CALL = {"llvm_ad_rgb": 2**25, "cuda_ad_rgb": 2**27}
ENV_ROWS, ENV_COLS = 8192, 8  # lat-long sky image (no azimuth dependence); the cone edge costs ~2/ENV_ROWS relative
KITTI_FROM_MITSUBA_CAM = np.diag([-1.0, -1.0, 1.0, 1.0])  # Mitsuba's camera: x left, y up, z forward


@dataclass(frozen=True)
class PTMesh:
    """One triangle mesh: vertices (n, 3) float32 world m (z up); faces (m, 3) uint32;
    albedo (n, 3) float32 linear RGB per vertex in [0, 1]; instance_id int (0 = terrain); material: per-pixel
    textures (pathtracer_textures.PTMaterial; albedo is then the vertex albedo before its scale and bias) or None."""

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray
    instance_id: int
    material: object | None = None


@dataclass(frozen=True)
class PTSpheres:
    """Small Lambertian spheres (marine snow): centres (n, 3) world m (stored as float32, the precision the path
    tracer takes them at); radii (n,) float64 m; albedo (n, 3) float32 linear RGB in [0, 1]."""

    centres: np.ndarray
    radii: np.ndarray
    albedo: np.ndarray


@dataclass(frozen=True)
class PTLamp:
    """A spot lamp in the water: position_world (3,) float64 m; direction_world (3,) unit; cutoff_deg and
    beam_width_deg half angles (degrees); intensity_rgb (3,) float64 radiant intensity on axis, W/sr, linear RGB."""

    position_world: np.ndarray
    direction_world: np.ndarray
    cutoff_deg: float
    beam_width_deg: float
    intensity_rgb: np.ndarray


@dataclass(frozen=True)
class PTLens:
    """A thin lens in place of the pinhole: Mitsuba's `thinlens` sensor, its aperture's radius (world m) and the
    distance to the plane in focus (z, world m). Mitsuba keeps the pinhole's field of view at every focus, so a
    lens of focal length f and f-number N focused at S has radius f / (2 N) * S / (S - f) here: the circle of
    confusion a real thin lens (whose image distance grows as it focuses closer) gives, in pixels."""

    aperture_radius_m: float
    focus_m: float


@dataclass(frozen=True)
class PTScene:
    """A scene to path-trace.

    K (3, 3) float64 pixels, pixel centres at integer coordinates; world_from_cam (4, 4) float64, KITTI camera axes
    (x right, y down, z forward); sigma_a, sigma_s (3,) 1/m; surface_z world m; sun_dir_world (3,) unit, towards the
    sun, already refracted; sun_irradiance_rgb (3,) just below the surface, on a plane normal to the beam;
    sky_radiance_rgb (3,) in-water radiance from directions within sky_cone_deg of +z, zero outside.
    """

    meshes: tuple[PTMesh, ...]
    K: np.ndarray
    width: int
    height: int
    world_from_cam: np.ndarray
    sigma_a: np.ndarray
    sigma_s: np.ndarray
    g: float
    surface_z: float
    sun_dir_world: np.ndarray
    sun_irradiance_rgb: np.ndarray
    sky_radiance_rgb: np.ndarray
    lamps: tuple[PTLamp, ...] = ()
    sky_cone_deg: float = 48.6
    # A flat port (camera_model.Slab as (5,) float64: inner_m, outer_m, air_index, glass_index, water_index): the camera
    # in air, glass between the camera frame's planes z = inner_m and z = outer_m, water beyond. None: no port.
    slab: np.ndarray | None = None
    spheres: PTSpheres | None = None
    lens: PTLens | None = None  # None: a pinhole


def find_libllvm() -> str:
    """The newest shared libLLVM with major version >= 16 on this machine; raises if there is none."""
    found: dict[str, int] = {}
    for pattern in LLVM_GLOBS:
        for path in glob.glob(pattern):
            m = re.fullmatch(r"libLLVM(?:-(\d+)[.\d]*)?\.so(?:\.(\d+)[.\d]*)?", os.path.basename(path))
            if m and (m.group(1) or m.group(2)):
                found[path] = int(m.group(1) or m.group(2))
    usable = {p: v for p, v in found.items() if v >= LLVM_MIN_MAJOR}
    if not usable:
        raise RuntimeError(
            f"Mitsuba's {VARIANT} variant needs a shared libLLVM >= {LLVM_MIN_MAJOR}; found "
            f"{sorted(found) or 'none'}. Install the Debian package libllvm19 (apt-get install libllvm19) "
            f"or set {LLVM_ENV} to such a library."
        )
    return max(usable, key=lambda p: (usable[p], os.path.basename(p).startswith("libLLVM-"), p))


def use_libllvm() -> str:
    """Point Dr.Jit at a usable libLLVM unless DRJIT_LIBLLVM_PATH is set; returns the path in effect.

    Dr.Jit reads the variable when drjit is first imported (importing mitsuba imports it), so call this before."""
    if not os.environ.get(LLVM_ENV):
        os.environ[LLVM_ENV] = find_libllvm()
    return os.environ[LLVM_ENV]


def load_mitsuba(variant: str = VARIANT):
    """The mitsuba module with `variant` set (llvm_ad_rgb: the CPU, after use_libllvm(); cuda_ad_rgb: an NVIDIA GPU)."""
    if variant not in MAX_SAMPLES_PER_CALL:
        raise ValueError(f"variant {variant!r}: use one of {', '.join(MAX_SAMPLES_PER_CALL)}")
    if variant.startswith("llvm"):
        use_libllvm()
    import mitsuba as mi

    mi.set_variant(variant)
    return mi


def _rgb(value: np.ndarray) -> dict:
    return {"type": "rgb", "value": [float(x) for x in np.asarray(value, dtype=np.float64)]}


def sky_image(sky_radiance_rgb: np.ndarray, cone_deg: float) -> np.ndarray:
    """(ENV_ROWS, ENV_COLS, 3) float32 lat-long radiance (Mitsuba layout, row 0 at the local +y pole): each row
    holds sky_radiance_rgb times the fraction of its polar-angle band inside the cone, so the edge is one row wide."""
    edges = np.linspace(0.0, 180.0, ENV_ROWS + 1)
    inside = np.clip((cone_deg - edges[:-1]) / (edges[1:] - edges[:-1]), 0.0, 1.0)
    rgb = inside[:, None] * np.asarray(sky_radiance_rgb, dtype=np.float64)[None, :]
    return np.ascontiguousarray(np.broadcast_to(rgb[:, None, :], (ENV_ROWS, ENV_COLS, 3)), dtype=np.float32)


def _check(scene: PTScene) -> None:
    K = np.asarray(scene.K, dtype=np.float64)
    if K[0, 1] != 0.0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise ValueError(f"PTScene.K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; got {K.tolist()}")
    if not np.isclose(K[0, 0], K[1, 1], rtol=1e-6, atol=0.0):
        raise ValueError(f"PTScene.K: Mitsuba's perspective camera needs square pixels, fx == fy; got fx={K[0, 0]}, "
                         f"fy={K[1, 1]}")
    R = np.asarray(scene.world_from_cam, dtype=np.float64)[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("PTScene.world_from_cam must be a rigid transform (a rotation and a translation)")
    points = [("camera", scene.world_from_cam[2, 3])] + [(f"lamp {i}", lamp.position_world[2])
                                                         for i, lamp in enumerate(scene.lamps)]
    for name, z in points:
        if not z < scene.surface_z:
            raise ValueError(f"PTScene: the {name} is at z={z}, not below surface_z={scene.surface_z}")


def _medium(scene: PTScene) -> dict:
    sigma_s = np.asarray(scene.sigma_s, dtype=np.float64)
    sigma_t = np.asarray(scene.sigma_a, dtype=np.float64) + sigma_s
    albedo = np.divide(sigma_s, sigma_t, out=np.zeros(3), where=sigma_t > 0)
    scale = max(float(sigma_t.max()), 1.0)  # Mitsuba reads an rgb sigma_t as a reflectance: keep it in [0, 1]
    return {
        "type": "homogeneous", "sigma_t": _rgb(sigma_t / scale), "albedo": _rgb(albedo), "scale": scale,
        "phase": {"type": "hg", "g": float(scene.g)},
    }


def _water_box(scene: PTScene, mi) -> tuple[dict, float]:
    """The `cube` holding the water (null boundary) and its horizontal half-size in metres: at least
    BOX_MIN_HALF_M and 10 mean free paths from the camera, and past every mesh (a far seabed)."""
    sigma_t = np.asarray(scene.sigma_a, dtype=np.float64) + np.asarray(scene.sigma_s, dtype=np.float64)
    half = max(BOX_MIN_HALF_M, 10.0 / sigma_t[sigma_t > 0].min()) if np.any(sigma_t > 0) else BOX_MIN_HALF_M
    cx, cy = (float(x) for x in scene.world_from_cam[:2, 3])
    for mesh in scene.meshes:
        v = np.asarray(mesh.vertices, np.float64)
        half = max(half, 1.01 * float(np.abs(v[:, :2] - [cx, cy]).max()) + 1.0)
    to_world = mi.ScalarTransform4f().translate([cx, cy, scene.surface_z - BOX_DEPTH_M / 2]).scale(
        [half, half, BOX_DEPTH_M / 2])  # `cube` spans [-1, 1]^3
    return {"type": "cube", "to_world": to_world, "bsdf": {"type": "null"},
            "interior": {"type": "ref", "id": "water"}}, half


def _mesh(mesh: PTMesh, name: str, mi):
    """An mi.Mesh built from arrays, two-sided Lambertian with per-vertex albedo, smooth (angle-weighted) normals;
    textured (pathtracer_textures) where the mesh has a material."""
    if mesh.material is not None:
        from seasynth.bench.pathtracer_textures import textured_mesh

        return textured_mesh(mesh, name, mi)
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "twosided", "material": {
        "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}})
    out = mi.Mesh(name, len(vertices), len(faces), props, has_vertex_normals=True)
    out.add_attribute("vertex_color", 3, mi.Float(np.asarray(mesh.albedo, dtype=np.float32).ravel()))
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()  # builds the acceleration data and recomputes vertex normals
    return out


def _spheres(spheres: PTSpheres | None) -> dict[str, dict]:
    """Mitsuba `sphere` shapes "sphere_000000", ..., diffuse with each one's albedo (seen from outside only)."""
    if spheres is None:
        return {}
    return {f"sphere_{i:06d}": {"type": "sphere", "center": [float(x) for x in c], "radius": float(r),
                                "bsdf": {"type": "diffuse", "reflectance": _rgb(a)}}
            for i, (c, r, a) in enumerate(zip(spheres.centres, spheres.radii, spheres.albedo))}


def _sensor(scene: PTScene, far_clip: float, mi) -> dict:
    K = np.asarray(scene.K, dtype=np.float64)
    w, h = int(scene.width), int(scene.height)
    # Mitsuba maps the film's x extent to x_fov and shifts the principal point by a fraction of the film size.
    offset = {"principal_point_offset_x": float(((w - 1) / 2.0 - K[0, 2]) / w),
              "principal_point_offset_y": float(((h - 1) / 2.0 - K[1, 2]) / h)}
    camera: dict = {"type": "perspective", **offset}
    if scene.lens is not None:
        if any(offset.values()):  # Mitsuba's thinlens has no principal point offset
            raise ValueError(f"PTScene.lens: Mitsuba's thinlens sensor needs the principal point at the image centre; "
                             f"K has cx={K[0, 2]}, cy={K[1, 2]} for {w}x{h}")
        camera = {"type": "thinlens", "aperture_radius": float(scene.lens.aperture_radius_m),
                  "focus_distance": float(scene.lens.focus_m)}
    return {
        **camera, "fov_axis": "x", "fov": float(np.degrees(2.0 * np.arctan(w / (2.0 * K[0, 0])))),
        "near_clip": NEAR_CLIP_M, "far_clip": far_clip,
        "to_world": mi.ScalarTransform4f(np.asarray(scene.world_from_cam, np.float64) @ KITTI_FROM_MITSUBA_CAM),
        **({"medium": {"type": "ref", "id": "water"}} if scene.slab is None else {}),
        "film": {"type": "hdrfilm", "width": w, "height": h, "pixel_format": "rgb", "component_format": "float32",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": 1},
    }


def _lamp(lamp: PTLamp, mi, scene: PTScene, housing_m: float) -> dict[str, dict]:
    """The spot emitter, and with housing_m > 0 a water-free sphere of that radius around it (a null boundary):
    no scattering vertex can then lie closer to the lamp than housing_m, which bounds the inverse-square weight of
    next-event estimation there. Without it multiply scattered lamp light has unbounded variance (fireflies that
    never average out). The lamp's intensity is scaled by exp(-a housing_m) per channel, what the water would have
    absorbed on the way out; the light it would have scattered within housing_m (b * housing_m of it, nearly all
    forwards at g ~ 0.9) is what the housing changes."""
    p = np.asarray(lamp.position_world, dtype=np.float64)
    d = np.asarray(lamp.direction_world, dtype=np.float64)
    up = [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0]
    intensity = np.asarray(lamp.intensity_rgb, dtype=np.float64)
    out: dict[str, dict] = {}
    if housing_m > 0:
        intensity = intensity * np.exp(-np.asarray(scene.sigma_a, dtype=np.float64) * housing_m)
        out["housing"] = {"type": "sphere", "center": p.tolist(), "radius": float(housing_m),
                          "bsdf": {"type": "null"}, "exterior": {"type": "ref", "id": "water"}}
    out["spot"] = {
        "type": "spot", "to_world": mi.ScalarTransform4f().look_at(origin=p.tolist(), target=(p + d).tolist(), up=up),
        "intensity": _rgb(intensity), "cutoff_angle": float(lamp.cutoff_deg), "beam_width": float(lamp.beam_width_deg),
    }
    if housing_m <= 0:
        out["spot"]["medium"] = {"type": "ref", "id": "water"}
    return out


def mitsuba_scene(scene: PTScene, max_depth: int = 64, rr_depth: int = 5, variant: str = VARIANT,
                  lamp_housing_m: float = 0.0, exact_nee: bool = False):
    """The mi.Scene for `scene`: water box, meshes (shape ids "mesh_0000", ... in order), spheres, sun, sky, lamps (each in
    a water-free sphere of radius lamp_housing_m when > 0: `_lamp`), camera. Integrated by Mitsuba's `volpath`, or
    with exact_nee by pathtracer_integrator's (the same expectation; shadow rays' transmittance taken exactly)."""
    _check(scene)
    mi = load_mitsuba(variant)
    box, half = _water_box(scene, mi)
    integrator = "volpath"
    if exact_nee:
        from seasynth.bench.pathtracer_integrator import register

        integrator = register(mi)
    d: dict = {
        "type": "scene", "water": _medium(scene), "water_box": box,
        "sensor": _sensor(scene, 10.0 * max(half, BOX_DEPTH_M), mi),
        "integrator": {"type": integrator, "max_depth": int(max_depth), "rr_depth": int(rr_depth)},
    }
    for i, mesh in enumerate(scene.meshes):
        d[f"mesh_{i:04d}"] = _mesh(mesh, f"mesh_{i:04d}", mi)
    d.update(_spheres(scene.spheres))
    if np.any(np.asarray(scene.sun_irradiance_rgb) > 0):
        d["sun"] = {"type": "directional", "direction": (-np.asarray(scene.sun_dir_world, np.float64)).tolist(),
                    "irradiance": _rgb(scene.sun_irradiance_rgb)}
    if np.any(np.asarray(scene.sky_radiance_rgb) > 0):
        d["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(sky_image(scene.sky_radiance_rgb, scene.sky_cone_deg)),
                    # the lat-long map's pole is local +y: turn it to world +z
                    "to_world": mi.ScalarTransform4f().rotate(axis=[1.0, 0.0, 0.0], angle=90.0)}
    if scene.slab is not None:
        from seasynth.bench.pathtracer_port import port_faces

        d.update(port_faces(scene, mi))
    for i, lamp in enumerate(scene.lamps):
        for part, value in _lamp(lamp, mi, scene, lamp_housing_m).items():
            d[f"lamp_{i:04d}_{part}"] = value
    return mi.load_dict(d)


def render(scene: PTScene, spp: int, seed: int = 0, max_depth: int = 64, rr_depth: int = 5,
           variant: str = VARIANT, lamp_housing_m: float = 0.0, exact_nee: bool = False) -> np.ndarray:
    """(h, w, 3) float32 linear radiance, the mean of `spp` box-filtered samples per pixel.

    Runs in calls of at most MAX_SAMPLES_PER_CALL samples in all (bounding memory), each seeded from (seed, call
    index) through np.random.SeedSequence, so different seeds give independent noise."""
    return render_seeds(scene, spp, (seed,), max_depth, rr_depth, variant, lamp_housing_m, exact_nee)[0]


def render_seeds(scene: PTScene, spp: int, seeds: tuple[int, ...], max_depth: int = 64, rr_depth: int = 5,
                 variant: str = VARIANT, lamp_housing_m: float = 0.0, exact_nee: bool = False) -> list[np.ndarray]:
    """`render` once per seed, the scene loaded into Mitsuba once: each image is render(scene, spp, seed)'s."""
    if spp < 1:
        raise ValueError(f"render: spp must be >= 1, got {spp}")
    ms = mitsuba_scene(scene, max_depth=max_depth, rr_depth=rr_depth, variant=variant, lamp_housing_m=lamp_housing_m,
                       exact_nee=exact_nee)
    mi = load_mitsuba(variant)
    per_call = max(1, MAX_SAMPLES_PER_CALL[variant] // (scene.width * scene.height))
    counts = [min(per_call, spp - start) for start in range(0, spp, per_call)]
    out = []
    for seed in seeds:
        total = np.zeros((scene.height, scene.width, 3), dtype=np.float64)
        for n, ss in zip(counts, np.random.SeedSequence(seed).spawn(len(counts))):
            image = mi.render(ms, spp=n, seed=int(ss.generate_state(1)[0]))
            total += n * np.asarray(image, dtype=np.float64)[..., :3]
        out.append((total / spp).astype(np.float32))
    return out


def render_ids(scene: PTScene, variant: str = VARIANT) -> np.ndarray:
    """(h, w) uint32 instance ids at pixel centres (0 where the centre ray hits terrain or nothing).

    Rays come from the Mitsuba sensor itself at film positions ((u + 0.5) / w, (v + 0.5) / h), so this checks the
    camera export as well as the geometry; through a port (PTScene.slab) each goes on as the port's faces' own
    dielectric BSDFs transmit it."""
    mi = load_mitsuba(variant)
    import drjit as dr

    ms = mitsuba_scene(scene, variant=variant)
    w, h = int(scene.width), int(scene.height)
    v, u = np.mgrid[0:h, 0:w]
    film = mi.Point2f(mi.Float(((u.ravel() + 0.5) / w).astype(np.float32)),
                      mi.Float(((v.ravel() + 0.5) / h).astype(np.float32)))
    ray, _ = ms.sensors()[0].sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    si = ms.ray_intersect(ray)
    shapes = {s.id(): s for s in ms.shapes()}
    ctx = mi.BSDFContext()
    for _ in range(2 * (scene.slab is not None)):  # through the port's two faces, by their own BSDFs
        port = (si.shape == mi.ShapePtr(shapes["port_inner"])) | (si.shape == mi.ShapePtr(shapes["port_outer"]))
        bs, _ = si.bsdf().sample(ctx, si, 0.9999, mi.Point2f(0.5, 0.5), port)  # 0.9999 > Fresnel's R: transmitted
        onward = si.spawn_ray(si.to_world(bs.wo))
        ray = mi.Ray3f(dr.select(port, onward.o, ray.o), dr.select(port, onward.d, ray.d))
        si = dr.select(port, ms.ray_intersect(ray), si)
    ids = np.zeros(h * w, dtype=np.uint32)
    for i, mesh in enumerate(scene.meshes):
        hit = np.asarray(si.shape == mi.ShapePtr(shapes[f"mesh_{i:04d}"]), dtype=bool)
        ids[hit] = mesh.instance_id
    return ids.reshape(h, w)
