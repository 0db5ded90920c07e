"""The surface pass and its resolve: the frame shaded (with range) into a multisampled float target, then the water
applied to each sample, each pixel's samples averaged and the outputs read back. Used by GLRenderer
(seasynth.worker.render.gl)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seasynth.service.errors import RenderError
from seasynth.worker.frame.formation import GLSL_HAZE
from seasynth.worker.frame.srgb import GLSL_SRGB8, SRGB8_THRESHOLDS_F32
from seasynth.worker.light import PhysicalLight
from seasynth.worker.light.glsl import SURFACE as PHYSICAL_SURFACE
from seasynth.worker.light.glsl import VOLUME
from seasynth.worker.render import depth, gl_light, materials, shaders
from seasynth.worker.render.readback import Pending, Readback


def surface_pass(
    r, view, items, lighting, water, sampling, *, want_clean=False, only_sample=-1, sample_range=False,
    want_nearest=False, srgb8=False, done=None, log=None,
):
    """Draw the surface pass and resolve it on GLRenderer `r` (its context current), and queue the reads of its
    outputs: SurfaceReads, whose fetch gives (image, clean or the one sample's range, nearest sample range), the last
    two None unless asked.

    only_sample: -1 averages each pixel's samples; k >= 0 takes sample k alone (audits). sample_range: the second
    output is that sample's range, before any water (audits), instead of the clean image. want_nearest: the nearest
    range any of a pixel's samples hits. srgb8: the image as 8-bit sRGB codes. done (if given) is called with
    "render" and "formation" as each part's GL commands are issued; log (if given) gets the passes drawn and
    attachments read."""
    GL = r.gl
    log = [] if log is None else log
    if sampling.msaa > r.max_samples:
        raise RenderError(f"{sampling.msaa}x MSAA asked for, {r.name} supports at most {r.max_samples}")
    ss, msaa = sampling.supersample, sampling.msaa
    W, H = view.width * ss, view.height * ss
    physical = isinstance(lighting, PhysicalLight)
    with_range = water is not None or physical or sample_range or want_nearest
    maps = gl_light.shadow_maps(r, view, items, lighting, log) if physical else None
    surf = r.targets.surface(W, H, msaa, with_range)
    # With range, the resolve reads where anything was drawn from the depth (still the clear's far where nothing
    # was) and takes colour 0 and range +inf there, so colour is not cleared: on an H100 a clear of 4 samples a
    # pixel took 1.2 ms of a 1080p frame's 6.2 (the pass costs the bytes it writes, not its shading).
    r.bind_and_clear(surf, ("keep",) if with_range else ("colour",))
    positions = r.sample_positions.get(msaa)
    if positions is None:  # the pattern is the implementation's, read once from a bound target of msaa samples
        positions = r.sample_positions[msaa] = depth.sample_positions(GL, msaa)
    if msaa > 1 and sampling.per_sample_shading:
        GL.glEnable(GL.GL_SAMPLE_SHADING)
        GL.glMinSampleShading(1.0)
    # Textured meshes are drawn by the program's textured variants (worker.render.materials), the rest by the
    # program itself, each group in the items' order.
    groups: dict[tuple[bool, int, bool], tuple[list, list]] = {}
    for item in items:
        for part in item.mesh.groups or ((0, None, item.mesh.material),):
            drawn, parts = groups.setdefault(materials.variant_key(part[2]), ([], []))
            drawn.append(item)
            parts.append(part)
    for (textured, mapping, orm), (group, parts) in groups.items():
        tex_defines = {"TEXTURED": textured, "MAPPING": mapping if textured else False, "HAS_ORM": orm,
                       "LOD_BIAS": textured and repr(materials.lod_bias(msaa, sampling.per_sample_shading))}
        if physical:
            prog, locs = r.programs.get(shaders.VERTEX, PHYSICAL_SURFACE, **gl_light.defines(lighting), **tex_defines)
            GL.glUseProgram(prog)
            r.set_view(locs, view, W, H)
            gl_light.surface_uniforms(r, locs, view, lighting, maps)
        else:
            prog, locs = r.programs.get(shaders.VERTEX, shaders.SURFACE, **tex_defines)
            GL.glUseProgram(prog)
            r.set_view(locs, view, W, H)
            sun_cam = view.cam_from_world[:3, :3] @ lighting.sun_dir_world
            GL.glUniform3fv(locs["u_sun_cam"], 1, sun_cam.astype(np.float32))
            GL.glUniform1f(locs["u_sun"], lighting.sun_intensity)
            GL.glUniform1f(locs["u_ambient"], lighting.ambient)
        r.draw(view, group, locs, lit=True, ids=False, parts=parts)
    GL.glDisable(GL.GL_SAMPLE_SHADING)
    log.append("surface+range" if len(surf.textures) > 1 else "surface")  # range: from the depth it keeps
    if done is not None:
        done("render")

    second = want_clean or sample_range
    # 8-bit codes are read back packed as RGB (unpacking RGBA on the CPU cost 23 ms a 1080p frame on llvmpipe,
    # reading RGB 4.5), so the NaN flag the codes carry in alpha is also written to an 8-bit slot of its own.
    nan_slot = 1 + second + want_nearest
    formats = ((GL.GL_RGBA8 if srgb8 else GL.GL_RGBA32F,) + (GL.GL_RGBA32F,) * second
               + (GL.GL_R32F,) * want_nearest + (GL.GL_R8,) * srgb8)
    res = r.targets.resolve(view.width, view.height, formats)
    compute = r.compute_resolve
    volume = physical and not sample_range  # audits (samples()) read J and range before any water
    if volume:
        src = shaders.RESOLVE.replace("HAZE_FUNCTION", VOLUME)
        extra_defines = {"PHYSICAL": True, **gl_light.defines(lighting)}
    else:
        src = shaders.RESOLVE.replace("HAZE_FUNCTION", GLSL_HAZE)
        extra_defines = {}
    src = src.replace("SRGB8_FUNCTION", GLSL_SRGB8).replace("RANGE_FUNCTION", depth.RANGE_FUNCTION)
    if compute:
        src = src.replace("#version 330 core", r.compute_header, 1)
    prog, locs = r.programs.get(
        None if compute else shaders.FULLSCREEN,
        src,
        **extra_defines,
        COMPUTE=compute,
        IMG_FORMAT=("rgba8" if srgb8 else "rgba32f") if compute else False,
        SAMPLES=msaa,
        SUPERSAMPLE=ss,
        RANGE_IN=with_range,
        WITH_HAZE=water is not None,
        WITH_CLEAN=want_clean and not sample_range,
        WITH_SAMPLE_RANGE=sample_range,
        WITH_NEAREST=want_nearest,
        NEAREST_LOCATION=1 + second,
        SRGB8_OUT=srgb8,
        NAN_LOCATION=nan_slot if srgb8 else False,
    )
    GL.glUseProgram(prog)
    tex_target = GL.GL_TEXTURE_2D_MULTISAMPLE if msaa > 1 else GL.GL_TEXTURE_2D
    for unit, (name, tex) in enumerate(zip(("u_J", "u_D"), surf.textures)):
        GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
        GL.glBindTexture(tex_target, tex)
        if name in locs:
            GL.glUniform1i(locs[name], unit)
    if with_range:
        depth.range_uniforms(GL, locs, view, positions)
    if water is not None:
        GL.glUniform3fv(locs["u_betaD"], 1, np.asarray(water.beta_D, np.float32))
        GL.glUniform3fv(locs["u_betaB"], 1, np.asarray(water.beta_B, np.float32))
        GL.glUniform3fv(locs["u_Binf"], 1, np.asarray(water.B_inf, np.float32))
    if volume:
        gl_light.volume_uniforms(r, locs, view, lighting)
    GL.glUniform1i(locs["u_only_sample"], only_sample)
    if srgb8:
        GL.glUniform1fv(locs["u_srgb_thr"], len(SRGB8_THRESHOLDS_F32), SRGB8_THRESHOLDS_F32)
    w, h = view.width, view.height
    if compute:
        for slot, (fmt, tex) in enumerate(zip(formats, res.textures)):
            GL.glBindImageTexture(slot, tex, 0, GL.GL_FALSE, 0, GL.GL_WRITE_ONLY, fmt)
        GL.glUniform2i(locs["u_size"], w, h)
        GL.glDispatchCompute((w + 7) // 8, (h + 7) // 8, 1)
        GL.glMemoryBarrier(GL.GL_FRAMEBUFFER_BARRIER_BIT | GL.GL_PIXEL_BUFFER_BARRIER_BIT)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, res.fbo)
    else:
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, res.fbo)
        GL.glDrawBuffers([GL.GL_COLOR_ATTACHMENT0 + slot for slot in range(len(formats))])
        GL.glDisable(GL.GL_DEPTH_TEST)
        GL.glViewport(0, 0, w, h)
        GL.glBindVertexArray(r.empty_vao)
        GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
        GL.glBindVertexArray(0)
        GL.glEnable(GL.GL_DEPTH_TEST)
    log.append("resolve+haze" if water is not None else "resolve+water" if volume else "resolve")
    rb = r.readback
    nan = rb.queue(nan_slot, w, h, GL.GL_RED, GL.GL_UNSIGNED_BYTE, np.uint8, 1) if srgb8 else None
    if srgb8:
        image = rb.queue(0, w, h, GL.GL_RGB, GL.GL_UNSIGNED_BYTE, np.uint8, 3)
        log.append("read image srgb8")
    else:
        image = rb.queue(0, w, h, GL.GL_RGB, GL.GL_FLOAT, np.float32, 3)
        log.append("read image")
    extra = nearest = None
    if second:
        extra = rb.queue(1, w, h, GL.GL_RGB, GL.GL_FLOAT, np.float32, 3)
        log.append("read sample range" if sample_range else "read clean")
    if want_nearest:
        nearest = rb.queue(1 + second, w, h, GL.GL_RED, GL.GL_FLOAT, np.float32, 1)
        log.append("read nearest range")
    if done is not None:
        done("formation")
    return SurfaceReads(image, extra, nearest, nan)


@dataclass
class SurfaceReads:
    """The surface pass's outputs, queued (seasynth.worker.render.readback): fetched after the frame's last pass."""

    image: Pending
    extra: Pending | None
    nearest: Pending | None
    nan: Pending | None  # 8-bit frames: where the linear colour was NaN

    def fetch(self, rb: Readback) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(image, clean or the one sample's range, nearest sample range), as surface_pass describes them: image
        (h, w, 3) float32 linear, or uint8 sRGB codes; clean (h, w, 3) float32 linear, or the sample's range in
        channel 0 (metres); nearest (h, w) float32 metres, +inf where no sample hits."""
        image = rb.fetch(self.image)
        extra = None if self.extra is None else rb.fetch(self.extra)
        nearest = None if self.nearest is None else rb.fetch(self.nearest)
        if self.nan is not None and rb.fetch(self.nan).any():
            raise ValueError("encode_srgb8: linear image contains NaN")  # as the CPU encoder says it
        return image, extra, nearest
