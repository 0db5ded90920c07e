"""A frame's sensor outputs besides the camera: which files each sensor writes, and one call that makes them all."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from seasynth.service.seeds import STREAM_FLS, STREAM_NAV, STREAM_SSS, frame_rng
from seasynth.service.shards import frame_file
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.sensors import Sensors
from seasynth.worker.scene.sample import Scene
from seasynth.worker.sensors import world_from_sensor
from seasynth.worker.sensors.fls import fls_frame
from seasynth.worker.sensors.nav import nav_record
from seasynth.worker.sensors.sss import sss_frame


def sensors_on(s: Sensors) -> bool:
    return s.fls.enabled or s.sss.enabled or s.any_nav


def surface_z(spec: DatasetSpec, scene: Scene, index: int) -> float:
    """World z of the water surface: the physical model's (drawn with the scene), else the first draw of the nav
    stream of the frame whose world this is from water.depth_m (the paper model draws no depth; that draw changes no
    camera output). A survey's frames share frame 0's world, so they share its surface too."""
    world = index if spec.trajectory.kind == "random" else 0
    drawn = float(frame_rng(spec.seed, world, STREAM_NAV).uniform(*spec.water.depth_m))
    return scene.light.medium.surface_z if scene.light is not None else drawn


@dataclass(frozen=True)
class SensorFrame:
    """Every sensor output of one frame: files as arrays ((h, w) uint16 PNGs) or text, and meta's `sensors` entry."""

    outputs: dict[str, np.ndarray | str]
    record: dict


def sensor_frame(spec: DatasetSpec, index: int, scene: Scene, items: list, renderer) -> SensorFrame:
    """The sensors' outputs of frame `index` (the camera's scene and draw items; the GL renderer)."""
    s = spec.sensors

    def path(part: str) -> str:
        return frame_file(part, index)

    outputs: dict[str, np.ndarray | str] = {}
    record: dict = {}
    surface = surface_z(spec, scene, index)
    objects = {p.instance_id: (p.role, p.class_name) for p in scene.objects}
    if s.fls.enabled:
        pose = world_from_sensor(scene.world_from_cam, s.fls.pose)
        fr = fls_frame(s.fls, s.acoustics, renderer, items, pose, objects, surface - float(pose[2, 3]),
                       frame_rng(spec.seed, index, STREAM_FLS))
        outputs[path("fls")] = fr.polar
        outputs[path("fls_fan")] = fr.fan
        outputs[path("fls_label")] = json.dumps({"objects": fr.labels}, indent=1, sort_keys=True) + "\n"
        record["fls"] = fr.record
    if s.sss.enabled:
        pose = world_from_sensor(scene.world_from_cam, s.sss.pose)
        fr = sss_frame(s.sss, s.acoustics, renderer, items, pose, objects, surface - float(pose[2, 3]),
                       frame_rng(spec.seed, index, STREAM_SSS))
        outputs[path("sss")] = fr.row
        outputs[path("sss_label")] = json.dumps({"objects": fr.labels}, indent=1, sort_keys=True) + "\n"
        record["sss"] = fr.record
    if s.any_nav:
        nav = nav_record(spec, index, scene, items, renderer, surface)
        outputs[path("nav")] = json.dumps(nav, indent=1, sort_keys=True) + "\n"
        record["nav"] = nav
    return SensorFrame(outputs=outputs, record=record)
