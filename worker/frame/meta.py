"""A frame's audit record (meta/NNNNNN.json): the seeds, versions, camera, water, lights and every object drawn."""

from __future__ import annotations

import dataclasses
import json

from seasynth import service
from seasynth.service.camera_model import CameraModel
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.frame.labels import FrameLabels
from seasynth.worker.render import Material, Sampling, View
from seasynth.worker.scene.sample import Placed, Scene
from seasynth.worker.sensors.outputs import SensorFrame


def frame_meta(spec: DatasetSpec, index: int, scene: Scene, view: View, sampling: Sampling, fl: FrameLabels | None,
               optics: dict, sensors: SensorFrame | None, renderer_name: str, versions: dict[str, str]) -> str:
    """The frame's audit record: nothing in it depends on time, host, duration, worker count, the dataset's
    frame count, shard size or the optional outputs depth/instance/clean/range (the dataset record holds the
    whole spec). With outputs.labels off there are no labels, so each object's label_line, visible_pixels
    and pixels_alone are null. optics: the effects' records by name (seasynth.worker.optics.Shot.record)."""
    record = {
        "dataset_seed": spec.seed,
        "frame_index": index,
        "code_version": service.__version__,
        "versions": versions,
        "gl_renderer": renderer_name,
        "preset": spec.quality,
        "sampling": dataclasses.asdict(sampling),
        "camera": {
            "K": view.K.tolist(),
            "width": view.width,
            "height": view.height,
            "pose_world_from_camera": scene.world_from_cam.tolist(),
            "clip": [view.near, view.far],
            "look_at": scene.look_at.tolist(),
            "look_at_instance": scene.look_at_instance,
            "position_draws": scene.camera_tries,
        },
        "water": _water_record(scene),
        "lights": {
            "sun_direction_world": scene.lighting.sun_dir_world.tolist(),
            "sun_intensity": scene.lighting.sun_intensity,
            "ambient": scene.lighting.ambient,
        },
        "terrain": {
            "key": scene.terrain.key,
            "albedo_scale": scene.terrain_albedo_scale.tolist(),
            "albedo_bias": scene.terrain_albedo_bias.tolist(),
        },
        **_material_record(scene.terrain.material, scene.terrain.tile_m, "terrain_material"),
        "objects": [_object_record(p, fl) for p in scene.objects],
        "objects_left_out": scene.dropped,
        # Each target class's objects drawn for this frame and left out of them (no free spot), in spec order.
        "targets": [{"class": name, "drawn": drawn, "left_out": left} for name, drawn, left in scene.class_counts],
        "noise": optics.get("noise"),
    }
    model = CameraModel.from_spec(spec.camera)
    if not model.pinhole:  # the port and distortion (seasynth.service.camera_model.CameraModel.from_record)
        record["camera"]["model"] = model.record()
    effects = {name: r for name, r in optics.items() if name != "noise"}
    if effects:  # absent with every camera and water-column effect off, so such frames' meta is unchanged
        record["optics"] = effects
    if sensors is not None:  # absent with every sensor off, so such frames' meta is unchanged
        record["sensors"] = sensors.record
    return json.dumps(record, indent=1, sort_keys=True) + "\n"


def _water_record(scene: Scene) -> dict | None:
    """meta's water: the model, the Jerlov type drawn, and every coefficient the frame used."""
    if scene.light is not None:
        return {"model": "physical", "jerlov_type": scene.water_type, **scene.light.coefficients()}
    w = scene.water
    if w is None:
        return None
    return {"model": "paper", "jerlov_type": scene.water_type, "beta_D": w.beta_D.tolist(),
            "beta_B": w.beta_B.tolist(), "B_inf": w.B_inf.tolist()}


def _material_record(m: Material | None, tile_m: float | None, name: str) -> dict:
    """{name: what a surface's per-pixel material is made of}, or {} where it has none (meta as before textures)."""
    if m is None:
        return {}
    images = {k: None if i is None else {"key": i.key, "source": i.source}
              for k, i in (("base", m.base), ("normal", m.normal), ("orm", m.orm))}
    record = {"mapping": m.mapping, "images": images, "base_gain": m.base_gain, "normal_scale": m.normal_scale,
              "occlusion_strength": m.occlusion_strength, "metallic_factor": m.metallic_factor,
              "anisotropy": m.anisotropy}
    if m.mapping == "triplanar":
        record["triplanar_per_m"] = m.triplanar_per_m
    if tile_m is not None:
        record["tile_m"] = tile_m
    return {name: record}


def _asset_record(key: str, source: str, sha256: str | None) -> dict:
    return {"key": key, "source": source, "sha256": sha256}


def _object_record(p: Placed, fl: FrameLabels | None) -> dict:
    return {
        "instance_id": p.instance_id,
        "class": p.class_name,
        "role": p.role,
        "placement": p.placement,
        "label_line": None if fl is None else fl.line_of.get(p.instance_id),
        "visible_pixels": None if fl is None else fl.visible.get(p.instance_id, 0),
        "pixels_alone": None if fl is None else fl.alone.get(p.instance_id),
        "asset": {**_asset_record(p.asset.key, p.asset.source, p.asset.sha256), "variant": p.variant},
        "scale": p.scale,
        "pose_world_from_object": p.world_from_obj.tolist(),
        "albedo_scale": p.albedo_scale.tolist(),
        "albedo_bias": p.albedo_bias.tolist(),
        **_material_record(p.material, None, "material"),
        **_surface_record(p),
    }


def _surface_record(p: Placed) -> dict:
    """{"materials": each face range of a user mesh with textures and what it draws with (None: vertex colours)},
    or {} for meshes without (meta as before textures)."""
    surface = p.surface if p.surface is not None else p.asset.surface
    if surface is None:
        return {}
    return {"materials": [{"first_face": first, "face_count": count,
                           "material": _material_record(m, None, "material").get("material")}
                          for first, count, m in surface.groups]}
