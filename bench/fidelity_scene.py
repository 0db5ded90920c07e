"""The fidelity bench's scenes for the path tracer: a seasynth frame exported as a PTScene (meshes with their albedo or
per-pixel materials, camera, sun, sky and lamps, the water), and the paper's deferred model's coefficients from the
same water."""

from __future__ import annotations

import math

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec

SEED, FRAME = 7, 3  # every configuration's scene: the example's frame FRAME under seed SEED


def path_traced_scene(session, spec: DatasetSpec):
    """The frame's scene for the path tracer, in its units (radiance: our J = albedo x irradiance is pi times less
    than a Lambertian surface's radiance under the same irradiance, so lights are scaled by pi)."""
    return exported_scene(session, spec, session.scene(spec, FRAME))


def exported_scene(session, spec: DatasetSpec, scene):
    """A sampled scene (water.model physical) of `spec` for the path tracer, in its units (path_traced_scene)."""
    from seasynth.bench.pathtracer import PTLamp, PTMesh, PTScene
    from seasynth.bench.pathtracer_textures import from_render_material
    from seasynth.worker.light import SNELL_CONE_DEG

    if scene.light is None:
        raise ValueError("the path tracer needs the physical light: water.enabled true and water.model physical")
    view = session.view(spec, scene)
    light = scene.light
    meshes = []
    for it in session.draw_items(scene):
        v = it.world_vertices().astype(np.float32)
        parts = it.mesh.groups or ((0, len(it.mesh.faces), it.mesh.material),)
        for first, count, material in parts:
            faces = it.mesh.faces[first:first + count]
            if material is None:
                meshes.append(PTMesh(vertices=v, faces=faces, albedo=it.shaded_albedo().astype(np.float32),
                                     instance_id=it.instance_id))
            else:
                meshes.append(PTMesh(vertices=v, faces=faces, albedo=it.mesh.albedo.astype(np.float32),
                                     instance_id=it.instance_id, material=from_render_material(material, it)))
    world_from_cam = scene.world_from_cam
    lamps = tuple(
        PTLamp(position_world=world_from_cam[:3, :3] @ lp.position_cam + world_from_cam[:3, 3],
               direction_world=world_from_cam[:3, :3] @ lp.direction_cam, cutoff_deg=math.degrees(lp.cutoff_rad),
               beam_width_deg=math.degrees(lp.beam_rad), intensity_rgb=math.pi * lp.intensity)
        for lp in light.lamps
    )
    sky = light.sky_irradiance / math.sin(math.radians(SNELL_CONE_DEG)) ** 2
    return PTScene(slab=port_slab(spec), spheres=particle_spheres(spec, scene, view),
                   meshes=tuple(meshes), K=view.K, width=view.width, height=view.height,
                   world_from_cam=world_from_cam, sigma_a=light.medium.a, sigma_s=light.medium.b, g=light.medium.g,
                   surface_z=light.medium.surface_z, sun_dir_world=light.sun_dir_world,
                   sun_irradiance_rgb=math.pi * light.sun_irradiance, sky_radiance_rgb=sky, lamps=lamps,
                   sky_cone_deg=SNELL_CONE_DEG, lens=thin_lens(spec, view))


def thin_lens(spec: DatasetSpec, view):
    """The camera's thin lens for the path tracer (bench.pathtracer.PTLens), or None for a pinhole."""
    from seasynth.bench.pathtracer import PTLens

    cam = spec.camera
    if cam.aperture_f is None:
        return None
    f = cam.focal_length_m(float(view.K[0, 0]), view.width)
    return PTLens(aperture_radius_m=f / (2.0 * cam.aperture_f) * cam.focus_m / (cam.focus_m - f), focus_m=cam.focus_m)


def port_slab(spec: DatasetSpec) -> np.ndarray | None:
    """PTScene.slab of the spec's camera: a flat port's slab, None without a port; the path tracer's camera is a
    pinhole, so a dome or a lens distortion is refused."""
    from seasynth.service.camera_model import CameraModel

    model = CameraModel.from_spec(spec.camera)
    if model.distortion.any() or model.kind == "dome":
        raise ValueError("the path tracer's camera is a pinhole behind at most a flat port: no dome, no distortion")
    if model.kind == "none":
        return None
    s = model.slab()
    return np.array([s.inner_m, s.outer_m, s.air_index, s.glass_index, s.water_index])


def particle_spheres(spec: DatasetSpec, scene, view):
    """The frame's marine snow (water.particles) as the path tracer's spheres: the rasteriser's particles with their
    true shape, same centres, diameters and albedo; None when off or none was drawn."""
    from seasynth.bench.pathtracer import PTSpheres
    from seasynth.worker.optics.particles import MarineSnow, frame_field

    if not MarineSnow().on(spec):
        return None
    field = frame_field(spec, FRAME, scene, view)
    if not len(field.diameters):
        return None
    world_from_cam = scene.world_from_cam
    return PTSpheres(centres=field.centres @ world_from_cam[:3, :3].T + world_from_cam[:3, 3],
                     radii=field.diameters / 2.0, albedo=np.repeat(field.albedo[:, None], 3, axis=1))


def paper_water(scene, view):
    """The deferred model's coefficients from the same water: beta_D = beta_B = c, and B_inf the physical model's
    open water looking horizontally at the camera's depth."""
    from seasynth.worker.light.volume import camera_depth, volume
    from seasynth.worker.render import WaterParams

    light = scene.light
    w = np.array([[1.0, 0.0, 0.0]])
    b_inf = volume(np.zeros((1, 3)), np.array([np.inf]), w, w, camera_depth(light, scene.world_from_cam), light)[0]
    c = light.medium.c
    return WaterParams(beta_D=c, beta_B=c, B_inf=b_inf)
