"""One frame as a pure function of (spec, dataset seed, frame index, renderer): files keyed by relative path."""

from __future__ import annotations

import io
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from seasynth.service.camera_model import CameraModel
from seasynth.service.seeds import frame_rng
from seasynth.service.shards import frame_file, frame_parts
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.scene import AssetRef, FileRef
from seasynth.service.spec.targets import Labels
from seasynth.worker.frame import kitti, labels
from seasynth.worker.frame.encode import encode_image, png_bytes
from seasynth.worker.frame.meta import frame_meta
from seasynth.worker.frame.srgb import decode_srgb8, encode_srgb8
from seasynth.worker.optics import Optics
from seasynth.worker.render import DrawItem, Material, Mesh, Passes, RenderResult, Sampling, View, ray_norms
from seasynth.worker.render.materials import tangent_frames
from seasynth.worker.scene.assets import Asset, UserSurface
from seasynth.worker.scene.assets.procedural import procedural_asset
from seasynth.worker.scene.assets.terrain import Terrain, with_material
from seasynth.worker.scene.assets.user import load_user_asset, load_user_terrain, load_user_texture
from seasynth.worker.scene.materials import (
    material_key,
    style_material,
    terrain_tile_m,
    terrain_uv,
    user_material,
)
from seasynth.worker.scene.sample import Placed, Scene, on_trajectory, sample_scene
from seasynth.worker.scene.variant_cache import VariantCache
from seasynth.worker.sensors.outputs import SensorFrame, sensor_frame, sensors_on

# Quality presets: how many samples make a pixel and where they are shaded. The water is always applied per
# sample, in float32, before samples are averaged in linear light. `fast` shades once per pixel at its centre
# (MSAA's usual shortcut); `default` and `high` shade every sample at its own position, so range and colour are
# right on silhouettes and across pixels where range varies. bench/ measures what each costs and how far it is
# from a 16-sample float64 reference.
PRESETS: dict[str, Sampling] = {
    "draft": Sampling(msaa=1, supersample=1, per_sample_shading=False),
    "fast": Sampling(msaa=4, supersample=1, per_sample_shading=False),
    "default": Sampling(msaa=4, supersample=1, per_sample_shading=True),
    "high": Sampling(msaa=4, supersample=2, per_sample_shading=True),
}

DEPTH_SCALE = 256.0  # KITTI depth PNG: metres * 256 in uint16, 0 = no measurement
VERSIONED_PACKAGES = ("numpy", "trimesh", "pyrender", "PyOpenGL", "Pillow", "imagecodecs")


def frame_paths(spec: DatasetSpec, index: int) -> list[str]:
    """Relative paths of every file frame `index` produces under `spec.outputs` and `spec.sensors`."""
    return [frame_file(part, index, spec.outputs.image_suffix) for part in frame_parts(spec)]


def to_render_mesh(key: str, mesh, material: Material | None = None, tile_m: float | None = None,
                   surface: UserSurface | None = None, warp: bool = True) -> Mesh:
    """GPU-ready arrays of a trimesh mesh whose vertex colours are sRGB-encoded uint8, with its material; tile_m:
    texture coordinates of a terrain (seasynth.worker.scene.materials.terrain_uv, warped unless `warp` is off) and
    their tangents; surface: a
    user mesh's texture coordinates and material groups, with their tangents."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    normals = np.nan_to_num(np.asarray(mesh.vertex_normals, dtype=np.float32))
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    uv = tangents = None
    if material is not None and tile_m is not None:
        uv = terrain_uv(v, tile_m, warp)
        tangents = tangent_frames(v, normals, uv, faces)
    if surface is not None:
        uv = surface.uv
        tangents = tangent_frames(v, normals, uv, faces)
    return Mesh(
        key=key,
        vertices=v.astype(np.float32),
        normals=normals,
        albedo=decode_srgb8(colours, np.float32),
        faces=faces,
        radius=float(np.linalg.norm(v - centre, axis=1).max()),
        centre=centre,
        material=material,
        groups=() if surface is None else surface.groups,
        uv=uv,
        tangents=tangents,
    )


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def depth_png16(range_m: np.ndarray, norms: np.ndarray) -> np.ndarray:
    """(h, w) uint16 KITTI depth: z-depth metres * 256, rounded; 0 where no surface or >= 256 m."""
    z = range_m.astype(np.float64) / norms
    ok = np.isfinite(z) & (z * DEPTH_SCALE < 65535.5) & (z > 0)
    out = np.zeros(z.shape, dtype=np.uint16)
    out[ok] = np.rint(z[ok] * DEPTH_SCALE).astype(np.uint16)
    return out


def scene_light(scene: Scene):
    """What the renderer shades with: the physical model's light, else the paper's lighting."""
    return scene.light if scene.light is not None else scene.lighting


class RenderSession:
    """Per-process resources: the GL renderer and caches of assets and uploaded meshes.

    fetch_asset maps an uploaded asset id (sha256) to a local file; only the service needs it. variant_folder: a
    folder where the render processes of one run share procedural terrain variants (seasynth.worker.scene.variant_cache).
    """

    def __init__(self, fetch_asset: Callable[[str], Path] | None = None, platform: str = "egl",
                 variant_folder: Path | str | None = None) -> None:
        self._fetch_asset = fetch_asset
        self._platform = platform
        self.variants = VariantCache(variant_folder)
        self._renderer = None
        self._meshes: dict[str, Mesh] = {}
        self._norms: dict[tuple, np.ndarray] = {}
        self.renderer_name = ""
        self.versions: dict[str, str] = {}

    def __enter__(self) -> RenderSession:
        from seasynth.worker.render.gl import GLRenderer

        self._renderer = GLRenderer(self._platform)
        self.renderer_name = self._renderer.name
        self.versions = {p: _version(p) for p in VERSIONED_PACKAGES}
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    @property
    def renderer(self):
        if self._renderer is None:
            raise RuntimeError("RenderSession used outside its `with` block")
        return self._renderer

    # ---- assets --------------------------------------------------------------------------------------------
    def _file(self, ref: FileRef) -> Path:
        if ref.path is not None:
            return Path(ref.path)
        if self._fetch_asset is None:
            raise FileNotFoundError(f"asset {ref.asset_id} is an uploaded asset; this session cannot fetch it")
        return self._fetch_asset(ref.asset_id)

    def asset_for(self, ref: AssetRef, variant: int | None) -> Asset:
        if ref.procedural is not None:
            return procedural_asset(ref.procedural, variant)
        return load_user_asset(self._file(ref))

    def terrain_for(self, spec: DatasetSpec, rng: np.random.Generator) -> Terrain:
        t = spec.terrain
        material = None
        if t.mesh is not None:
            terrain = load_user_terrain(self._file(t.mesh))
        else:
            style = t.styles[rng.integers(len(t.styles))]
            variant = int(rng.integers(t.variants))
            terrain = self.variants.terrain(style, variant, t.size_m, t.cells, t.relief_m)
            material = style_material(style, variant, spec)
        if t.texture is not None:  # a user's texture set: its colour replaces the terrain's
            files = [None if ref is None else load_user_texture(self._file(ref))
                     for ref in (t.texture, t.normal_map, t.height_map)]
            material = user_material(*files, t.height_map_m, t.texture_tile_m, float(spec.materials.anisotropy))
        if material is None:
            return terrain
        tile_m = terrain_tile_m(material, spec)
        return with_material(terrain, material, material_key(material), t.texture is not None, tile_m, t.anti_tiling)

    def _render_mesh(self, key: str, mesh, material: Material | None = None, tile_m: float | None = None,
                     surface: UserSurface | None = None, warp: bool = True) -> Mesh:
        """The render mesh of a trimesh under `key` (with a material: key and material's key; with a user surface:
        key and its materials' keys), cached; tile_m: terrain texture coordinates repeating every tile_m metres
        (seasynth.worker.scene.materials.terrain_uv)."""
        if material is not None:
            key = f"{key}+{material_key(material)}" + ("" if warp else "/unwarped")
        if surface is not None:
            key = f"{key}+" + ";".join(material_key(m) for _, _, m in surface.groups)
        got = self._meshes.get(key)
        if got is None:
            got = self._meshes[key] = to_render_mesh(key, mesh, material, tile_m, surface, warp)
        return got

    def _ray_norms(self, view: View) -> np.ndarray:
        key = (view.width, view.height, view.K.tobytes())
        if key not in self._norms:
            self._norms[key] = ray_norms(view.K, view.width, view.height)
        return self._norms[key]

    # ---- frames --------------------------------------------------------------------------------------------
    def scene(self, spec: DatasetSpec, index: int) -> Scene:
        if spec.trajectory.kind == "random":
            return sample_scene(spec, frame_rng(spec.seed, index), self.asset_for, self.terrain_for)
        # A survey: one world (frame 0's draws) for every frame, seen from the trajectory's pose at this frame.
        return on_trajectory(sample_scene(spec, frame_rng(spec.seed, 0), self.asset_for, self.terrain_for),
                             spec, index)

    def view(self, spec: DatasetSpec, scene: Scene) -> View:
        return View(
            K=np.asarray(spec.camera.K(), dtype=np.float64),
            width=spec.camera.width,
            height=spec.camera.height,
            cam_from_world=scene.cam_from_world,
            near=spec.camera.clip[0],
            far=spec.camera.clip[1],
        )

    def draw_items(self, scene: Scene) -> list[DrawItem]:
        t = scene.terrain
        items = [
            DrawItem(
                mesh=self._render_mesh(t.key, t.mesh, t.material, t.tile_m, warp=t.uv_warp),
                world_from_obj=np.eye(4),
                albedo_scale=scene.terrain_albedo_scale,
                albedo_bias=scene.terrain_albedo_bias,
                instance_id=0,
            )
        ]
        if scene.far_field is not None:  # the seabed beyond the tile: unlabelled like it, and it shadows nothing drawn
            items.append(
                DrawItem(
                    mesh=self._render_mesh(scene.far_field.key, scene.far_field.mesh, t.material, t.tile_m,
                                           warp=t.uv_warp),
                    world_from_obj=np.eye(4),
                    albedo_scale=scene.terrain_albedo_scale,
                    albedo_bias=scene.terrain_albedo_bias,
                    instance_id=0,
                    casts_shadows=False,
                )
            )
        for p in scene.objects:
            items.append(
                DrawItem(
                    mesh=self._render_mesh(p.asset.key, p.asset.mesh, p.material, surface=p.surface),
                    world_from_obj=p.world_from_obj,
                    albedo_scale=p.albedo_scale,
                    albedo_bias=p.albedo_bias,
                    instance_id=p.instance_id,
                )
            )
        return items

    def frame_files(
        self, spec: DatasetSpec, index: int, mark: Callable[[str], None] | None = None
    ) -> dict[str, bytes]:
        """Every file of frame `index`, keyed by its relative path (`image_2/000123.png` or `.jpg`, ...).

        mark: benchmarks pass a stopwatch, called with each finished stage's name.
        """
        timer = mark
        mark = mark or (lambda stage: None)
        scene = self.scene(spec, index)
        view = self.view(spec, scene)
        items = self.draw_items(scene)
        mark("sampling")
        o = spec.outputs
        optics = Optics(spec, index, scene, view, items)
        # Without effects that need the float image, its 8-bit codes come from the GPU.
        needs = optics.shot.needs
        passes = Passes(clean=o.clean or "clean" in needs, ids=o.labels or o.instance or o.semantic or "ids" in needs,
                        range=o.range or o.depth or "range" in needs, srgb8=not optics.float_image)
        light, preset = scene_light(scene), PRESETS[spec.quality]
        result = optics.render(
            lambda v, drawn: self.renderer.render(v, drawn, light, scene.water, preset, passes, mark=timer))
        image = result.image
        frame_labels = self.labels(view, scene, items, result, spec.labels, optics) if o.labels else None
        mark("labels")
        # Sonar and navigation sensors, each from its own seed stream: switching one on changes no camera byte.
        sensors = None
        if sensors_on(spec.sensors):
            sensors = sensor_frame(spec, index, scene, items, self.renderer)
            mark("sensors")

        def path(part: str) -> str:
            return frame_file(part, index, o.image_suffix)

        image8 = encode_srgb8(image) if optics.float_image else image
        files: dict[str, bytes] = {path("image"): encode_image(image8, o)}
        if o.labels:
            files[path("label")] = kitti.format_label_file(frame_labels.objects).encode()
        files[path("calib")] = kitti.format_calib(view.K).encode()
        if o.meta:
            files[path("meta")] = self.meta(spec, index, scene, view, frame_labels, optics.record, sensors).encode()
        if o.depth:
            norms = self._ray_norms(view) if optics.shot.range_norms is None else optics.shot.range_norms
            files[path("depth")] = png_bytes(depth_png16(result.range_m, norms))
        if o.instance:
            files[path("instance")] = png_bytes(result.instance.astype(np.uint16))
        if o.semantic:
            files[path("semantic")] = png_bytes(semantic_ids(result.instance, scene, spec.class_names))
        if o.clean:
            files[path("clean")] = png_bytes(encode_srgb8(result.clean))
        if o.range:
            files[path("range")] = npy_bytes(result.range_m)
        if sensors is not None:
            for rel, data in sensors.outputs.items():
                files[rel] = png_bytes(data) if isinstance(data, np.ndarray) else data.encode()
        mark("encode")
        return files

    def labels(self, view: View, scene: Scene, items: list[DrawItem], result: RenderResult,
               filters: Labels | None = None, optics: Optics | None = None) -> labels.FrameLabels:
        """KITTI objects of the targets with at least one visible pixel, in instance-id order: a target below the
        filters (spec labels; None: the defaults, which keep every one) is a DontCare line with its 2D box.
        optics: the frame's effects, which count the pixels of objects alone as its image was made (a port or a
        distorting lens resamples them) and project for truncation through its camera model."""
        filters = Labels() if filters is None else filters
        model = CameraModel.from_spec(optics.shot.spec.camera) if optics is not None else None
        to_pixels = None if model is None or model.pinhole else model.project
        boxes = labels.tight_boxes(result.instance)
        objects, line_of, visible, alone = [], {}, {}, {}
        by_id = {it.instance_id: it for it in items}
        shown = [(p, boxes[p.instance_id], _points_cam(view, p)) for p in scene.objects
                 if p.role == "target" and p.instance_id in boxes]
        jobs = [(by_id[p.instance_id], _pixel_region(pts, view)) for p, _, pts in shown]
        counts = self.renderer.pixels_alone_many(view, jobs) if optics is None else optics.pixels_alone(
            self.renderer, jobs)
        for (p, box, pts), alone_px in zip(shown, counts):
            # Rendered alone an object covers at least what it covers among others (same rasterisation).
            alone_px = max(alone_px, box.pixels)
            truncated = labels.truncation(pts, view.K, view.width, view.height, view.near, to_pixels)
            occluded = labels.occlusion_level(box.pixels, alone_px)
            line_of[p.instance_id] = len(objects)
            visible[p.instance_id] = box.pixels
            alone[p.instance_id] = alone_px
            if labels.labelled(box.pixels, alone_px, filters.min_visible_px, filters.min_visible_fraction):
                objects.append(labels.kitti_object(p.class_name, box, labels.box3d(pts), truncated, occluded))
            else:
                objects.append(labels.dont_care(box))
        return labels.FrameLabels(objects=objects, line_of=line_of, visible=visible, alone=alone)

    def meta(self, spec, index, scene: Scene, view: View, fl: labels.FrameLabels | None, optics: dict,
             sensors: SensorFrame | None = None) -> str:
        """The frame's audit record (seasynth.worker.frame.meta.frame_meta) as JSON text."""
        return frame_meta(spec, index, scene, view, PRESETS[spec.quality], fl, optics, sensors, self.renderer_name,
                          self.versions)


def semantic_ids(instance: np.ndarray, scene: Scene, class_names: tuple[str, ...]) -> np.ndarray:
    """(h, w) uint8 class ids of an (h, w) instance id image: i + 1 on the pixels of targets of the i-th class,
    0 elsewhere (terrain, water, distractors)."""
    lut = np.zeros(max([0, *(p.instance_id for p in scene.objects)]) + 1, dtype=np.uint8)
    index = {name: k + 1 for k, name in enumerate(class_names)}
    for p in scene.objects:
        if p.role == "target":
            lut[p.instance_id] = index[p.class_name]
    return lut[instance]


def _points_cam(view: View, p: Placed) -> np.ndarray:
    """(n, 3) float64: the object's vertices in the camera frame, metres."""
    T = view.cam_from_world @ p.world_from_obj
    v = np.asarray(p.asset.mesh.vertices, dtype=np.float64)
    return v @ T[:3, :3].T + T[:3, 3]


def _pixel_region(points_cam: np.ndarray, view: View) -> tuple[int, int, int, int] | None:
    """Inclusive pixel bounds containing the projection of points all in front of the near plane, else None."""
    if np.any(points_cam[:, 2] <= view.near):
        return None
    uv = labels.project(points_cam, view.K)
    lo = np.floor(uv.min(axis=0)).astype(int) - 1
    hi = np.ceil(uv.max(axis=0)).astype(int) + 1
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _version(package: str) -> str:
    try:
        return version(package)
    except PackageNotFoundError:
        return "unknown"
