"""The physical model's GL side: shadow maps for the sun and lamps, and the uniforms of the surface and resolve
passes (`seasynth.worker.light.glsl`). Used by GLRenderer; only frames with water.model physical reach it."""

from __future__ import annotations

import numpy as np

from seasynth.worker.light import PhysicalLight
from seasynth.worker.light.glsl import MAX_LAMPS, SOFT_SHADOW_RADIUS_M
from seasynth.worker.light.lamps import cone_energy
from seasynth.worker.light.sky import sky_phase_table
from seasynth.worker.light.solved import table_block, view_azimuth_frame
from seasynth.worker.light.volume import camera_depth
from seasynth.worker.render import DrawItem, View, shadows
from seasynth.worker.render.shaders import DEPTH_ONLY, VERTEX

SHADOW_UNIT = 3  # texture units from here on hold shadow maps (the resolve's colour and depth use 0 and 1)
TABLE_BINDING = 0  # the uniform block binding of the resolve's solved view table


def defines(light: PhysicalLight) -> dict[str, object]:
    t = light.terms
    return {
        "WITH_SUN": t.sun,
        "WITH_SUN_SHADOW": t.sun and t.sun_shadows,
        "WITH_CAUSTICS": t.sun and t.caustics,
        "WITH_SKY": t.sky,
        "WITH_SCATTER": t.scattering,
        "LAMPS": t.lamps,
        "LAMP_SPREAD": t.lamps > 0 and t.lamp_spread,
        "WITH_SOLVED": t.solved,
    }


def _shadow_target(r, size: int, slot: int):
    GL = r.gl

    def build():
        t = r.targets.new_fbo()
        tex = GL.glGenTextures(1)
        before = int(GL.glGetIntegerv(GL.GL_TEXTURE_BINDING_2D))  # the active unit keeps what a pass bound there
        GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
        GL.glTexStorage2D(GL.GL_TEXTURE_2D, 1, GL.GL_DEPTH_COMPONENT32F, size, size)
        for k, v in ((GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR), (GL.GL_TEXTURE_MAG_FILTER, GL.GL_LINEAR),
                     (GL.GL_TEXTURE_WRAP_S, GL.GL_CLAMP_TO_EDGE), (GL.GL_TEXTURE_WRAP_T, GL.GL_CLAMP_TO_EDGE),
                     (GL.GL_TEXTURE_COMPARE_MODE, GL.GL_COMPARE_REF_TO_TEXTURE),
                     (GL.GL_TEXTURE_COMPARE_FUNC, GL.GL_LEQUAL)):
            GL.glTexParameteri(GL.GL_TEXTURE_2D, k, v)
        GL.glBindTexture(GL.GL_TEXTURE_2D, before)
        GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_TEXTURE_2D, tex, 0)
        GL.glDrawBuffers([GL.GL_NONE])
        GL.glReadBuffer(GL.GL_NONE)
        t.textures.append(tex)
        return t

    return r.targets.get(("shadow", size, slot), build)


def _draw_depth(r, clip_from_world: np.ndarray, items: list[DrawItem], size: int, slot: int) -> int:
    """Draw a shadow map; returns its depth texture."""
    GL = r.gl
    t = _shadow_target(r, size, slot)
    with r.clip_control.conventional():  # the maps' samplers compare GL's own depth (LEQUAL)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, t.fbo)
        GL.glViewport(0, 0, size, size)
        GL.glClear(GL.GL_DEPTH_BUFFER_BIT)
        prog, locs = r.programs.get(VERTEX, DEPTH_ONLY)
        GL.glUseProgram(prog)
        GL.glUniformMatrix4fv(locs["u_proj"], 1, GL.GL_TRUE, np.eye(4, dtype=np.float32))
        GL.glEnable(GL.GL_POLYGON_OFFSET_FILL)
        GL.glPolygonOffset(2.0, 4.0)
        for it in items:
            gpu = r.mesh(it.mesh)
            M = (clip_from_world @ it.world_from_obj).astype(np.float32)
            GL.glUniformMatrix4fv(locs["u_cam_from_obj"], 1, GL.GL_TRUE, M)
            GL.glBindVertexArray(gpu.vao)
            GL.glDrawElements(GL.GL_TRIANGLES, gpu.count, GL.GL_UNSIGNED_INT, None)
        GL.glBindVertexArray(0)
        GL.glDisable(GL.GL_POLYGON_OFFSET_FILL)
    return t.textures[0]


def shadow_maps(r, view: View, items: list[DrawItem], light: PhysicalLight, log: list[str]) -> dict:
    """Draw the shadow maps the frame's terms need: {"sun": (texture, map_from_cam, clip_from_world, coarse
    texture, its size) or None,
    "lamps": [(texture, map_from_cam), ...]} (map_from_cam: camera frame -> map coordinates, see shadows)."""
    out: dict = {"sun": None, "lamps": []}
    world_from_cam = np.linalg.inv(view.cam_from_world)
    t = light.terms
    items = [it for it in items if it.casts_shadows]  # the maps span what casts shadows, not the far seabed
    if t.sun and t.sun_shadows:
        clip = shadows.sun_clip_from_world(light.sun_dir_world, [it.bounding_sphere() for it in items])
        tex = _draw_depth(r, clip, items, shadows.SUN_MAP_SIZE, 0)
        soft_size = shadows.soft_map_size(clip, SOFT_SHADOW_RADIUS_M)
        soft = _draw_depth(r, clip, items, soft_size, MAX_LAMPS + 1)
        out["sun"] = (tex, shadows.texture_from_clip(clip) @ world_from_cam, clip, soft, soft_size)
        log.append("sun shadow")
    for i, lamp in enumerate(light.lamps[: t.lamps]):
        clip_cam = shadows.lamp_clip_from_cam(lamp.position_cam, lamp.direction_cam, lamp.cutoff_rad, view.far)
        tex = _draw_depth(r, clip_cam @ view.cam_from_world, items, shadows.LAMP_MAP_SIZE, 1 + i)
        out["lamps"].append((tex, shadows.texture_from_clip(clip_cam)))
        log.append(f"lamp{i} shadow")
    return out


def _set(GL, locs, name, fn, *args):
    if name in locs:
        fn(locs[name], *args)


def _vec3(GL, locs, name, v) -> None:
    _set(GL, locs, name, GL.glUniform3fv, 1, np.asarray(v, np.float32))


def _common(GL, locs, light: PhysicalLight) -> None:
    m = light.medium
    _vec3(GL, locs, "u_c", m.c)
    _vec3(GL, locs, "u_K", m.k)
    _vec3(GL, locs, "u_b", m.b)
    _set(GL, locs, "u_g", GL.glUniform1f, float(m.g))
    _set(GL, locs, "u_mu_w", GL.glUniform1f, float(light.sun_dir_world[2]))
    _vec3(GL, locs, "u_E0", light.sun_irradiance)
    _vec3(GL, locs, "u_Esky", light.sky_irradiance)
    for i, lamp in enumerate(light.lamps[:MAX_LAMPS]):
        _vec3(GL, locs, f"u_lamp_pos[{i}]", lamp.position_cam)
        _vec3(GL, locs, f"u_lamp_dir[{i}]", lamp.direction_cam)
        _vec3(GL, locs, f"u_lamp_I[{i}]", lamp.intensity)
        _set(GL, locs, f"u_lamp_cone[{i}]", GL.glUniform2f, lamp.beam_rad, lamp.cutoff_rad)
        _set(GL, locs, f"u_lamp_energy[{i}]", GL.glUniform1f, cone_energy(lamp))


def surface_uniforms(r, locs: dict[str, int], view: View, light: PhysicalLight, maps: dict) -> None:
    GL = r.gl
    world_from_cam = np.linalg.inv(view.cam_from_world)
    _common(GL, locs, light)
    row = world_from_cam[2].astype(np.float32)
    _set(GL, locs, "u_world_z", GL.glUniform4f, *row.tolist())
    _set(GL, locs, "u_surface_z", GL.glUniform1f, float(light.medium.surface_z))
    _vec3(GL, locs, "u_sun_cam", view.cam_from_world[:3, :3] @ light.sun_dir_world)
    if light.terms.caustics:
        _caustic_uniforms(GL, locs, light, world_from_cam)
    if light.terms.solved:
        table = light.column.depth_table()
        for name, values in (("u_ed_sun", table.sun), ("u_ed_sky", table.sky)):
            _set(GL, locs, name, GL.glUniform3fv, len(values), np.ascontiguousarray(values, dtype=np.float32))
        _set(GL, locs, "u_ed_step", GL.glUniform1f, float(table.step_m))
    _set(GL, locs, "u_pixel_angle", GL.glUniform1f, float(1.0 / min(view.K[0, 0], view.K[1, 1])))
    units = []
    if maps["sun"] is not None:
        tex, map_from_cam, clip, soft, soft_size = maps["sun"]
        units += [("u_sun_shadow", tex), ("u_sun_soft", soft)]
        _set(GL, locs, "u_sun_from_cam", GL.glUniformMatrix4fv, 1, GL.GL_TRUE, map_from_cam.astype(np.float32))
        _set(GL, locs, "u_sun_texel_m", GL.glUniform1f, shadows.sun_texel_m(clip, shadows.SUN_MAP_SIZE))
        # The forward-scattered sun blurs shadows by about SOFT_SHADOW_RADIUS_M, the coarse map's texel.
        _set(GL, locs, "u_sun_soft_texel_m", GL.glUniform1f, shadows.sun_texel_m(clip, soft_size))
    for i, (tex, map_from_cam) in enumerate(maps["lamps"]):
        units.append((f"u_lamp_shadow[{i}]", tex))
        _set(GL, locs, f"u_lamp_from_cam[{i}]", GL.glUniformMatrix4fv, 1, GL.GL_TRUE, map_from_cam.astype(np.float32))
        _set(GL, locs, f"u_lamp_texel[{i}]", GL.glUniform1f, shadows.lamp_texel(light.lamps[i].cutoff_rad))
    for k, (name, tex) in enumerate(units):
        GL.glActiveTexture(GL.GL_TEXTURE0 + SHADOW_UNIT + k)
        GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
        _set(GL, locs, name, GL.glUniform1i, SHADOW_UNIT + k)
    GL.glActiveTexture(GL.GL_TEXTURE0)


def _caustic_uniforms(GL, locs: dict[str, int], light: PhysicalLight, world_from_cam: np.ndarray) -> None:
    c = light.caustics
    for name, row in (("u_world_x", 0), ("u_world_y", 1)):
        _set(GL, locs, name, GL.glUniform4f, *world_from_cam[row].astype(np.float32).tolist())
    _vec3(GL, locs, "u_sun_world", light.sun_dir_world)
    for i in range(len(c.phase)):
        _set(GL, locs, f"u_caustic_k[{i}]", GL.glUniform2f, *(c.k[i] / (2 * np.pi)).astype(np.float32).tolist())
        _set(GL, locs, f"u_caustic_phase[{i}]", GL.glUniform1f, float(c.phase[i] / (2 * np.pi)))
        _set(GL, locs, f"u_caustic_amp[{i}]", GL.glUniform1f, float(c.amplitude[i]))
    for name, value in (("u_caustic_norm", c.norm), ("u_caustic_focal", c.focal_depth_m),
                        ("u_caustic_blur", c.blur_per_m2)):
        _set(GL, locs, name, GL.glUniform1f, float(value))


def volume_uniforms(r, locs: dict[str, int], view: View, light: PhysicalLight) -> None:
    GL = r.gl
    world_from_cam = np.linalg.inv(view.cam_from_world)
    _common(GL, locs, light)
    _vec3(GL, locs, "u_sun_world", light.sun_dir_world)
    _set(GL, locs, "u_cam_depth", GL.glUniform1f, camera_depth(light, world_from_cam))
    if light.terms.sky and light.terms.scattering:
        table = sky_phase_table(light.medium.g).astype(np.float32)
        _set(GL, locs, "u_sky_phase", GL.glUniform1fv, len(table), table)
    _set(GL, locs, "u_world_from_cam", GL.glUniformMatrix3fv, 1, GL.GL_TRUE,
         world_from_cam[:3, :3].astype(np.float32))
    t = light.terms
    if t.solved and t.scattering and (t.sun or t.sky):
        block = table_block(light.column.view_table(camera_depth(light, world_from_cam), t.sun, t.sky))
        prog = int(GL.glGetIntegerv(GL.GL_CURRENT_PROGRAM))
        index = GL.glGetUniformBlockIndex(prog, "ViewTableBlock")
        if index != GL.GL_INVALID_INDEX:
            if r.view_table_buffer is None:
                r.view_table_buffer = GL.glGenBuffers(1)
            GL.glUniformBlockBinding(prog, index, TABLE_BINDING)
            GL.glBindBuffer(GL.GL_UNIFORM_BUFFER, r.view_table_buffer)
            GL.glBufferData(GL.GL_UNIFORM_BUFFER, block.nbytes, block, GL.GL_STREAM_DRAW)
            GL.glBindBufferBase(GL.GL_UNIFORM_BUFFER, TABLE_BINDING, r.view_table_buffer)
        _set(GL, locs, "u_sun_azimuth", GL.glUniform2f, *view_azimuth_frame(light.sun_dir_world).tolist())
