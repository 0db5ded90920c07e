"""Scene sampling: terrain, targets and distractors on the surface, camera, light, water, all from one rng."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from seasynth.service.camera_model import CameraModel
from seasynth.service.errors import AssetError, SeasynthError, SpecError
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.scene import AssetRef, Distractors
from seasynth.service.spec.targets import InWater, Seabed, Targets
from seasynth.service.water import jerlov_beta, jerlov_veiling_light
from seasynth.worker.light import PhysicalLight
from seasynth.worker.light.build import sample_physical
from seasynth.worker.render import Lighting, Material, WaterParams
from seasynth.worker.scene.assets import Asset, UserSurface
from seasynth.worker.scene.assets.terrain import Terrain
from seasynth.worker.scene.far_field import FarField, far_field, seabed_of
from seasynth.worker.scene.materials import albedo_factor, asset_material, user_surface
from seasynth.worker.scene.placement import Pose, in_box, neighbours, place, place_school
from seasynth.worker.scene.poses import look_at_pose, rigid_inverse
from seasynth.worker.scene.trajectory import vehicle_state
from seasynth.worker.sensors import world_from_sensor

CAMERA_TRIES = 64  # per frame, before the frame is refused
CAMERA_CLEARANCE_M = 0.05  # the camera, and each enabled sensor, keeps at least this far above the terrain and
# outside objects


class SceneError(SeasynthError):
    """A frame whose workspaces admit no valid scene (e.g. every camera position is inside geometry)."""


# What says that a spec or its files cannot render (a 422 to an API client), as opposed to rendering failing.
INPUT_ERRORS = (SpecError, AssetError, SceneError)


@dataclass(frozen=True)
class Placed:
    """One object on, in or above the terrain (seasynth.worker.scene.placement)."""

    instance_id: int  # 1.. in placement order (targets first); 0 is reserved for terrain and open water
    role: str  # "target" or "distractor"
    class_name: str | None  # the spec's class name for targets, None for distractors
    asset: Asset
    variant: int | None
    scale: float
    world_from_obj: np.ndarray  # (4, 4) float64, metres, world z up
    albedo_scale: np.ndarray  # (3,) float32
    albedo_bias: np.ndarray  # (3,) float32
    footprint_m: float  # metres: radius of the disc about the anchor holding the object's horizontal projection
    material: Material | None = None  # per-pixel textures of a procedural asset (seasynth.worker.scene.materials)
    surface: UserSurface | None = None  # a user mesh's own textures, filtered as the spec says (materials.user_surface)
    z_span: tuple[float, float] = (-math.inf, math.inf)  # world metres, lowest and highest (placement's rule)
    placement: dict | None = None  # for meta: {"kind": ..., and what the placement drew}; None: not recorded


@dataclass(frozen=True)
class Scene:
    terrain: Terrain
    terrain_albedo_scale: np.ndarray  # (3,) float32
    terrain_albedo_bias: np.ndarray  # (3,) float32
    objects: tuple[Placed, ...]
    world_from_cam: np.ndarray  # (4, 4) float64, KITTI camera axes (x right, y down, z forward)
    look_at: np.ndarray  # (3,) float64 world
    look_at_instance: int | None
    camera_tries: int  # camera positions drawn until one was outside all geometry
    lighting: Lighting  # as drawn, in air (the paper's model shades with it directly)
    water: WaterParams | None  # the paper's model
    water_type: str | None
    dropped: int  # objects left out because no free spot was found
    light: PhysicalLight | None = None  # the physical model (then water is None)
    far_field: FarField | None = None  # the seabed beyond the terrain, if spec.terrain.far_field
    # Per target class in spec order: (class name, objects drawn, objects left out for want of a free spot)
    class_counts: tuple[tuple[str, int, int], ...] = ()

    @property
    def cam_from_world(self) -> np.ndarray:
        return rigid_inverse(self.world_from_cam)


AssetSource = Callable[[AssetRef, int], Asset]


def uniform3(rng: np.random.Generator, lo, hi) -> np.ndarray:
    return rng.uniform(np.asarray(lo, np.float64), np.asarray(hi, np.float64))


def _sample_water(spec: DatasetSpec, rng: np.random.Generator) -> tuple[WaterParams | None, str | None]:
    w = spec.water
    if not w.enabled:
        return None, None
    kind = w.jerlov[rng.integers(len(w.jerlov))] if w.jerlov else None
    if w.beta_D is not None:
        beta_D = uniform3(rng, w.beta_D.min, w.beta_D.max)
    else:
        beta_D = jerlov_beta(kind) * rng.uniform(*w.beta_jitter)
    if w.beta_B is not None:
        beta_B = uniform3(rng, w.beta_B.min, w.beta_B.max)
    else:
        beta_B = beta_D * rng.uniform(*w.backscatter_ratio)
    if w.B_inf is not None:
        B_inf = uniform3(rng, w.B_inf.min, w.B_inf.max)
    else:
        B_inf = jerlov_veiling_light(kind) * rng.uniform(*w.B_inf_jitter)
    # The type is drawn whatever the ranges (so the draw order stays fixed) but recorded only when it was used.
    used = w.beta_D is None or w.B_inf is None
    return WaterParams(beta_D=beta_D, beta_B=beta_B, B_inf=B_inf), kind if used else None


def sample_scene(spec: DatasetSpec, rng: np.random.Generator, asset_for: AssetSource, terrain_for) -> Scene:
    """Draw one frame's scene. Every draw comes from `rng`, in a fixed order that no output option changes. A survey
    (trajectory.kind other than random) draws no camera: its pose is the trajectory's at frame 0 (on_trajectory
    moves it to any frame)."""
    tex = spec.texture
    terrain = terrain_for(spec, rng)
    t_scale = rng.uniform(*tex.scale, size=3).astype(np.float32)
    t_bias = rng.uniform(*tex.bias, size=3).astype(np.float32)

    placed: list[Placed] = []
    counts, dropped = [], 0
    for group, role in [*((cls, "target") for cls in spec.targets), (spec.distractors, "distractor")]:
        new, drawn = _place_group(spec, rng, terrain, asset_for, group, role, placed)
        placed += new
        dropped += drawn - len(new)
        if role == "target":
            counts.append((group.class_name, drawn, drawn - len(new)))

    spheres = [_bounding_sphere(p) for p in placed]
    if spec.trajectory.kind == "random":
        world_from_cam, look_at, look_id, tries = _draw_camera(spec, rng, terrain, placed, spheres)
    else:  # a survey's pose is its trajectory's (frame 0 here, see on_trajectory): no draw, so no workspace fails it
        world_from_cam = vehicle_state(spec.trajectory, 0).world_from_vehicle
        look_at, look_id, tries = world_from_cam[:3, 3] + world_from_cam[:3, 2], None, 0

    lt = spec.lighting
    elev = math.radians(rng.uniform(*lt.sun_elevation_deg))
    azim = math.radians(rng.uniform(*lt.sun_azimuth_deg))
    lighting = Lighting(
        sun_dir_world=np.array([math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim), math.sin(elev)]),
        sun_intensity=float(rng.uniform(*lt.sun_intensity)),
        ambient=float(rng.uniform(*lt.ambient)),
    )
    water, water_type, light = None, None, None
    if spec.water.enabled and spec.water.resolved_model == "physical":
        top_z = max([float(terrain.mesh.bounds[1][2])] + [c[2] + r for c, r in spheres])
        light, water_type = sample_physical(spec, rng, lighting, top_z, _seabed(terrain, t_scale, t_bias))
    else:
        water, water_type = _sample_water(spec, rng)
    return Scene(
        terrain=terrain,
        terrain_albedo_scale=t_scale,
        terrain_albedo_bias=t_bias,
        objects=tuple(placed),
        world_from_cam=world_from_cam,
        look_at=look_at,
        look_at_instance=look_id,
        camera_tries=tries,
        lighting=lighting,
        water=water,
        water_type=water_type,
        light=light,
        dropped=dropped,
        class_counts=tuple(counts),
        far_field=far_field(terrain, float(spec.camera.clip[1])) if spec.terrain.far_field else None,
    )


@functools.lru_cache(maxsize=64)
def _seabed_of(terrain: Terrain):  # as many terrains as far_field keeps: every one a spec draws
    return seabed_of(terrain)


def _seabed(terrain: Terrain, scale: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, float]:
    """The seabed's mean albedo (3,) (its colours' mean in linear light times its maps' mean factor, the frame's
    randomisation applied) and the world z of its mean plane, for the solved water column."""
    seabed = _seabed_of(terrain)
    return np.clip(seabed.mean_rgb * albedo_factor(terrain.material) * scale + bias, 0.0, 1.0), seabed.mean_z


def _place_group(spec: DatasetSpec, rng: np.random.Generator, terrain: Terrain, asset_for: AssetSource,
                 group: Targets | Distractors, role: str, before: list[Placed]) -> tuple[list[Placed], int]:
    """(the objects placed, how many were drawn) of a target class or the distractors, clear of the objects
    placed `before` and of each other, numbered after them. Per object: asset, variant, scale, albedo, then its
    pose, in that order (schools: the school's size and spacing first, then its members' draws, then their
    poses)."""
    box = spec.workspaces.targets if role == "target" else spec.workspaces.distractors
    placement = getattr(group, "placement", Seabed(kind="seabed"))
    school = placement.school if isinstance(placement, InWater) else None
    n = int(rng.integers(group.count[0], group.count[1] + 1))
    drawn, new = 0, []
    for _ in range(n):
        size = 1 if school is None else int(rng.integers(school.size[0], school.size[1] + 1))
        members = [_draw_object(spec, rng, asset_for, group) for _ in range(size)]
        drawn += size
        others = neighbours([*before, *new])
        if school is None:
            poses = [place(rng, terrain, box, members[0][1], members[0][2], placement, others)]
        else:
            poses = place_school(rng, terrain, box, [(m[1], m[2]) for m in members], placement, others)
        for (ref, asset, scale, variant, a_scale, a_bias), pose in zip(members, poses):
            if pose is not None:
                new.append(_placed(spec, len(before) + len(new) + 1, role, group, placement, asset, variant, scale,
                                   a_scale, a_bias, pose))
    return new, drawn


def _draw_object(spec: DatasetSpec, rng: np.random.Generator, asset_for: AssetSource, group):
    """(asset ref, asset, scale, variant, albedo scale (3,), albedo bias (3,)) of one object, drawn in that order."""
    tex = spec.texture
    ref = group.assets[rng.integers(len(group.assets))]
    variant = int(rng.integers(ref.variants)) if ref.procedural is not None else None
    asset = asset_for(ref, variant)
    scale = float(rng.uniform(*group.scale))
    a_scale = rng.uniform(*tex.scale, size=3).astype(np.float32)
    a_bias = rng.uniform(*tex.bias, size=3).astype(np.float32)
    return ref, asset, scale, variant, a_scale, a_bias


def _placed(spec: DatasetSpec, instance_id: int, role: str, group, placement, asset: Asset, variant: int | None,
            scale: float, a_scale: np.ndarray, a_bias: np.ndarray, pose: Pose) -> Placed:
    return Placed(
        instance_id=instance_id,
        role=role,
        class_name=group.class_name if role == "target" else None,
        asset=asset,
        variant=variant,
        scale=scale,
        world_from_obj=pose.world_from_obj,
        albedo_scale=a_scale,
        albedo_bias=a_bias,
        footprint_m=pose.footprint_m,
        material=asset_material(asset, variant, spec),
        surface=user_surface(asset, spec),
        z_span=pose.z_span,
        placement={"kind": placement.kind, **pose.drawn},
    )


def _draw_camera(spec: DatasetSpec, rng: np.random.Generator, terrain: Terrain, placed: list[Placed],
                 spheres: list) -> tuple[np.ndarray, np.ndarray, int | None, int]:
    """A random-pose frame's camera: (world_from_cam (4, 4) float64, look_at (3,) float64 world, its target's
    instance id or None, positions drawn). Looks at a random target inside the look-at workspace, else at a random
    point of that workspace's seabed, from the first position in workspaces.camera clear of all geometry."""
    ws = spec.workspaces
    centres = np.array([p.world_from_obj[:3, 3] for p in placed if p.role == "target"]).reshape(-1, 3)
    ids = [p.instance_id for p in placed if p.role == "target"]
    inside = np.flatnonzero(in_box(centres, ws.look_at)) if centres.size else np.array([], int)
    if inside.size:
        pick = int(inside[rng.integers(inside.size)])
        look_at, look_id = centres[pick].copy(), ids[pick]
    else:  # a point of the seabed inside the look-at workspace
        look_at, look_id = uniform3(rng, ws.look_at.min, ws.look_at.max), None
        ground = float(terrain.height_at(look_at[None, :2])[0])
        look_at[2] = min(max(ground, ws.look_at.min[2]), ws.look_at.max[2])
    look_at = look_at + rng.normal(0.0, spec.camera.look_at_jitter_m, size=3)

    on_look_at = 0  # draws refused only for lying on the look-at point (a camera there has no direction)
    housing = CameraModel.from_spec(spec.camera).housing_points()
    for tries in range(1, CAMERA_TRIES + 1):
        eye = uniform3(rng, ws.camera.min, ws.camera.max)
        if _camera_clear(eye, look_at, terrain, spheres, spec.camera.clip[0], housing):
            T = look_at_pose(eye, look_at)
            if _sensor_inside(T, spec, terrain, spheres) is None:
                return T, look_at, look_id, tries
        on_look_at += bool(np.linalg.norm(look_at - eye) < 1e-3)
    if on_look_at == CAMERA_TRIES:
        raise SceneError(f"workspaces.camera: all {CAMERA_TRIES} positions drawn lie within 1 mm of the point the "
                         f"camera looks at (workspaces.look_at {look_at.round(6).tolist()}, camera.look_at_jitter_m "
                         f"{spec.camera.look_at_jitter_m}): the camera has no direction to look in")
    also = " with every enabled sensor (sensors.*.pose) outside them too" if spec.sensors.enabled_poses() else ""
    port = " with camera.port's housing clear of them" if housing.size else ""
    raise SceneError(f"workspaces.camera: no camera position outside the terrain and objects{also} after "
                     f"{CAMERA_TRIES} draws{port}")


def _bounding_sphere(p: Placed) -> tuple[np.ndarray, float]:
    v = np.asarray(p.asset.mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre_obj = (lo + hi) / 2
    radius = float(np.linalg.norm(v - centre_obj, axis=1).max()) * p.scale
    return p.world_from_obj[:3, :3] @ centre_obj + p.world_from_obj[:3, 3], radius


def _camera_clear(eye, look_at, terrain: Terrain, spheres, near: float, housing: np.ndarray) -> bool:
    """The camera is above the terrain, outside every object's bounding sphere and not on its look-at point, and
    so is its port's housing (housing: CameraModel.housing_points, camera frame)."""
    if not (np.linalg.norm(look_at - eye) >= 1e-3 and _clear(eye, terrain, spheres, near)):
        return False
    return _housing_clear(look_at_pose(eye, look_at), housing, terrain, spheres)


def _housing_clear(world_from_cam: np.ndarray, housing: np.ndarray, terrain: Terrain, spheres) -> bool:
    """Every housing point (camera frame) is CAMERA_CLEARANCE_M above the terrain and outside every object's
    bounding sphere by as much, with the camera at world_from_cam: nothing lies inside the housing."""
    if not housing.size:
        return True
    p = housing @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    ground = terrain.height_at(p[:, :2])
    if np.any(np.isfinite(ground) & (p[:, 2] < ground + CAMERA_CLEARANCE_M)):
        return False
    return all(bool(np.all(np.linalg.norm(p - c, axis=1) > r + CAMERA_CLEARANCE_M)) for c, r in spheres)


def _sensor_inside(world_from_vehicle: np.ndarray, spec: DatasetSpec, terrain: Terrain,
                   spheres) -> tuple[str, np.ndarray] | None:
    """(name, world position (3,)) of the first enabled sensor that is not as clear of the terrain and objects as
    the camera must be, with the vehicle at world_from_vehicle (4, 4); None when every one is."""
    for name, pose in spec.sensors.enabled_poses().items():
        p = world_from_sensor(world_from_vehicle, pose)[:3, 3]
        if not _clear(p, terrain, spheres, spec.camera.clip[0]):
            return name, p
    return None


def _clear(eye, terrain: Terrain, spheres, near: float) -> bool:
    """eye (3,) world is CAMERA_CLEARANCE_M + near above the terrain and outside every object's bounding sphere."""
    ground = float(terrain.height_at(eye[None, :2])[0])
    if math.isfinite(ground) and eye[2] < ground + CAMERA_CLEARANCE_M + near:
        return False
    return all(np.linalg.norm(eye - c) > r + CAMERA_CLEARANCE_M + near for c, r in spheres)


def on_trajectory(scene: Scene, spec: DatasetSpec, index: int) -> Scene:
    """The scene seen from the trajectory's vehicle pose at frame `index` (seasynth.worker.scene.trajectory), which must lie above
    the terrain and outside every object, as must each enabled sensor."""
    import dataclasses

    state = vehicle_state(spec.trajectory, index)
    T = state.world_from_vehicle
    eye = T[:3, 3]
    spheres = [_bounding_sphere(p) for p in scene.objects]
    housing = CameraModel.from_spec(spec.camera).housing_points()
    if not (_camera_clear(eye, eye + T[:3, 2], scene.terrain, spheres, spec.camera.clip[0], housing[:0])
            and _housing_clear(T, housing, scene.terrain, spheres)):
        port = " (or camera.port's housing reaches them)" if housing.size else ""
        raise SceneError(f"trajectory: frame {index}'s vehicle position {eye.round(3).tolist()} is inside the terrain "
                         f"or an object{port}; raise trajectory.altitude_m")
    inside = _sensor_inside(T, spec, scene.terrain, spheres)
    if inside is not None:
        name, p = inside
        raise SceneError(f"sensors.{name}.pose.offset_m: at frame {index} the {name} sits at {p.round(3).tolist()}, "
                         "inside the terrain or an object; raise trajectory.altitude_m or move the sensor")
    return dataclasses.replace(scene, world_from_cam=T, look_at=eye + T[:3, 2], look_at_instance=None, camera_tries=0)
