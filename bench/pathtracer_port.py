"""A flat port in the path tracer (seasynth.bench.pathtracer.PTScene.slab): the camera in air behind two dielectric
faces, the water beyond, and the housing's black inside behind the lens."""

from __future__ import annotations

import numpy as np


def port_faces(scene, mi) -> dict[str, dict]:
    """A flat port's two faces as dielectric rectangles across the camera's whole field: the inner one (normal
    towards the camera) between air and glass, the outer one between glass and the water (its exterior medium).
    Their Fresnel reflections are traced too (about 4% at air-acrylic), which seasynth's rasteriser leaves out; what
    they send back ends on the housing's black inside behind the lens (without it, it went on through air, no
    medium, to the sky: a bright disc where the reflected rays fell in Snell's window)."""
    inner, outer, air, glass, water = (float(x) for x in scene.slab)
    K = np.asarray(scene.K, dtype=np.float64)
    slope = max(abs(-0.5 - K[0, 2]), abs(scene.width - 0.5 - K[0, 2]), abs(-0.5 - K[1, 2]),
                abs(scene.height - 0.5 - K[1, 2])) / K[0, 0]
    half = 2.0 * outer * slope * np.sqrt(2.0) + 0.01  # metres: past every camera ray
    world = np.asarray(scene.world_from_cam, np.float64)

    def face(z: float, flip: bool, ext_ior: float) -> dict:
        to_world = world @ np.diag([half, half, 1.0, 1.0])
        to_world[:3, 3] = world[:3, :3] @ [0.0, 0.0, z] + world[:3, 3]
        return {"type": "rectangle", "to_world": mi.ScalarTransform4f(to_world), "flip_normals": flip,
                "bsdf": {"type": "dielectric", "int_ior": glass, "ext_ior": ext_ior}}

    out = {"port_inner": face(inner, True, air), "port_outer": face(outer, False, water)}
    out["port_outer"]["exterior"] = {"type": "ref", "id": "water"}
    back = face(-0.25 * inner, False, air)  # the housing's black inside: what the faces reflect back ends there
    back.update(to_world=mi.ScalarTransform4f(np.asarray(back["to_world"].matrix) @ np.diag([3, 3, 1, 1])),
                bsdf={"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
    return {**out, "port_housing": back}
