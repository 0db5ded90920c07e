"""Per-pixel materials: texture images on the GPU (mipmapped, anisotropically filtered, within a memory budget),
the GLSL that samples them in the surface pass, and tangent frames for normal maps.

A textured mesh is drawn by a variant of the surface program compiled with TEXTURED and MAPPING (0: the mesh's
texture coordinates, 1: triplanar in the object frame); an untextured one by the program as it always was, so
frames without textures are unchanged. Every image is bound: a material without a normal map binds a flat one
with normal_scale 0, without a base colour a white one, without occlusion/metal a white one.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from seasynth.service.errors import RenderError
from seasynth.worker.render import Image, Material

TEXTURE_BUDGET_BYTES = 1024 * 2**20  # textures with their mipmaps, per renderer; least recently drawn first out
MAX_ANISOTROPY = 16.0
MATERIAL_UNIT = 10  # base colour, normal, orm on units 10, 11, 12 (shadow maps use 3..8, the resolve 0 and 1)
UPLOAD_UNIT = 13  # where images are bound while they upload
MAPPINGS = {"uv": 0, "triplanar": 1}

# 1x1 images standing in for a material's absent ones: white colour (factor 1), a flat normal, occlusion 1 and
# metal 1 (times metallic_factor).
WHITE = Image("material/white", np.full((1, 1, 3), 255, np.uint8), True, "built-in white")
FLAT = Image("material/flat-normal", np.array([[[128, 128, 255]]], np.uint8), False, "built-in flat normal")
ORM_ONE = Image("material/orm-one", np.full((1, 1, 3), 255, np.uint8), False, "built-in occlusion 1")

UNIFORMS = ("u_base_tex", "u_normal_tex", "u_orm_tex", "u_material", "u_triplanar_per_m")

# Vertex stage additions (shaders.VERTEX under TEXTURED): texture coordinates, the tangent in the camera frame and
# the object-frame position and normal for triplanar mapping.
VERTEX_IN = """
#ifdef TEXTURED
layout(location = 3) in vec2 a_uv;
layout(location = 4) in vec4 a_tan;
out vec2 v_uv;
out vec4 v_tan;
out vec3 v_obj;
out vec3 v_obj_nrm;
#endif
"""
VERTEX_MAIN = """
#ifdef TEXTURED
    v_uv = a_uv;
    v_tan = vec4(mat3(u_cam_from_obj) * a_tan.xyz, a_tan.w);
    v_obj = a_pos;
    v_obj_nrm = a_nrm;
#endif
"""

# Fragment stage: `vec3 textured_albedo(inout vec3 n, out float occlusion)` gives the pixel's albedo and perturbs
# the camera-frame normal n (already facing the camera) by the normal map.
FRAGMENT = """
#ifdef TEXTURED
in vec2 v_uv;
in vec4 v_tan;
in vec3 v_obj;
in vec3 v_obj_nrm;
uniform sampler2D u_base_tex;
uniform sampler2D u_normal_tex;
uniform sampler2D u_orm_tex;
uniform vec4 u_material;        // base_gain, normal_scale, occlusion_strength, metallic_factor
uniform float u_triplanar_per_m;
uniform mat3 u_nrm_cam;
#ifndef LOD_BIAS
#define LOD_BIAS 0.0
#endif
vec3 unpack_normal(vec3 t) { return vec3((t.xy * 2.0 - 1.0) * u_material.y, t.z * 2.0 - 1.0); }
// The length of a filtered normal-map lookup: its texels are unit normals, so a footprint over relief averages to
// a shorter one, and a Lambertian surface's mean shading over the footprint is that length times the shading of
// the mean direction (irradiance linear in the normal). 8-bit texels leave a unit normal's length up to ~2/255 off 1:
// lengths count from there. normal_scale s tilts each texel's normal s times as far, which for small tilts makes
// 1 - length s^2 times as large.
float spread(vec3 t) {
    float l = min(length(t * 2.0 - 1.0) * (255.0 / 253.0), 1.0);
    return max(1.0 - u_material.y * u_material.y * (1.0 - l), 0.0);
}
vec3 textured_albedo(inout vec3 n, out float occlusion) {
    float len = length(v_nrm);
    float side = dot(n, v_nrm) < 0.0 ? -1.0 : 1.0;   // n faces the camera: the back of a face takes -normal
#if MAPPING == 0
    vec3 base = texture(u_base_tex, v_uv, LOD_BIAS).rgb;
#ifdef HAS_ORM
    vec3 orm = texture(u_orm_tex, v_uv, LOD_BIAS).rgb;
#else
    vec3 orm = vec3(1.0);
#endif
    vec3 t = texture(u_normal_tex, v_uv, LOD_BIAS).xyz;
    vec3 m = unpack_normal(t);
    float relief = spread(t);
    if (len > 1e-20 && dot(v_tan.xyz, v_tan.xyz) > 1e-20) {
        vec3 N = v_nrm / len;
        vec3 T = v_tan.xyz - N * dot(N, v_tan.xyz);
        float tl = length(T);
        if (tl > 1e-12) {
            T /= tl;
            vec3 B = cross(N, T) * (v_tan.w < 0.0 ? -1.0 : 1.0);   // the image's up (glTF)
            n = side * normalize(T * m.x + B * m.y + N * m.z);
        }
    }
#else
    // Triplanar (Golus's whiteout blend): projections onto the object frame's yz, xz and xy planes, weighted by the
    // object-frame normal to the fourth power.
    vec3 on = v_obj_nrm / max(length(v_obj_nrm), 1e-20);
    vec3 w = pow(abs(on), vec3(4.0));
    w /= max(w.x + w.y + w.z, 1e-20);
    vec3 p = v_obj * u_triplanar_per_m;
    float relief = 1.0;
    vec2 ux = p.zy, uy = p.xz, uz = p.xy;
    vec3 base = w.x * texture(u_base_tex, ux, LOD_BIAS).rgb + w.y * texture(u_base_tex, uy, LOD_BIAS).rgb
              + w.z * texture(u_base_tex, uz, LOD_BIAS).rgb;
#ifdef HAS_ORM
    vec3 orm = w.x * texture(u_orm_tex, ux, LOD_BIAS).rgb + w.y * texture(u_orm_tex, uy, LOD_BIAS).rgb
             + w.z * texture(u_orm_tex, uz, LOD_BIAS).rgb;
#else
    vec3 orm = vec3(1.0);
#endif
    if (len > 1e-20) {
        // the maps' y points up the image, towards -t: the projections' second axis runs with t, so y flips
        vec3 flip = vec3(1.0, -1.0, 1.0);
        vec3 sx = texture(u_normal_tex, ux, LOD_BIAS).xyz;
        vec3 sy = texture(u_normal_tex, uy, LOD_BIAS).xyz;
        vec3 sz = texture(u_normal_tex, uz, LOD_BIAS).xyz;
        relief = w.x * spread(sx) + w.y * spread(sy) + w.z * spread(sz);
        vec3 tx = unpack_normal(sx) * flip;
        vec3 ty = unpack_normal(sy) * flip;
        vec3 tz = unpack_normal(sz) * flip;
        tx = vec3(tx.xy + on.zy, abs(tx.z) * on.x);
        ty = vec3(ty.xy + on.xz, abs(ty.z) * on.y);
        tz = vec3(tz.xy + on.xy, abs(tz.z) * on.z);
        vec3 obj = normalize(tx.zyx * w.x + ty.xzy * w.y + tz.xyz * w.z);
        n = side * normalize(u_nrm_cam * obj);
    }
#endif
    occlusion = 1.0 + u_material.z * (orm.r - 1.0);
    return base * (u_material.x * (1.0 - u_material.w * orm.b) * relief);
}
#endif
"""


def lod_bias(msaa: int, per_sample_shading: bool) -> float:
    """The mip level bias of textures shaded at each of `msaa` samples of a pixel: each sample's filter covers
    1/sqrt(msaa) of the pixel's width (the samples' average covers the rest), so textures are not blurred twice.
    Shaded once a pixel: none."""
    return -0.5 * float(np.log2(msaa)) if per_sample_shading and msaa > 1 else 0.0


def variant_key(material: Material | None) -> tuple[bool, int, bool]:
    """(TEXTURED, MAPPING, HAS_ORM) defines of the program that draws a mesh with this material: a material without
    an occlusion/roughness/metal image reads none (occlusion 1, metallic_factor as given)."""
    if material is None:
        return (False, 0, False)
    if material.mapping not in MAPPINGS:
        raise RenderError(f"unknown material mapping {material.mapping!r}; known: {', '.join(MAPPINGS)}")
    return (True, MAPPINGS[material.mapping], material.orm is not None)


def image_bytes(image: Image) -> int:
    """GPU bytes of an image with its mipmap chain (4 bytes a texel: drivers keep RGB8 as RGBA8)."""
    h, w = image.pixels.shape[:2]
    return int(h * w * 4 * 4 // 3)


@dataclass
class GpuImage:
    texture: int
    nbytes: int
    used: int  # the renderer call that last bound it
    anisotropy: float = 1.0  # its sampler's GL_TEXTURE_MAX_ANISOTROPY now


class Textures:
    """The texture images of one GL context, uploaded on first use with a full mipmap chain, trilinear and
    anisotropic filtering (each material's anisotropy, up to MAX_ANISOTROPY where the context has it and
    `anisotropic`) and repeat wrapping;
    least recently bound first out past budget_bytes, never one bound by the call in progress. Every call needs the
    context current.

    Software rasterisers filter trilinearly only (GLRenderer passes anisotropic=False): llvmpipe's anisotropic path
    took 49.5 s to draw a 160x120 frame of the default example that it draws in 0.6 s without it, at 2x as at 16x
    (Mesa 22, LLVM 15, 2 cores)."""

    def __init__(self, gl, renderer_name: str, budget_bytes: int = TEXTURE_BUDGET_BYTES, anisotropic: bool = True
                 ) -> None:
        if budget_bytes < 0:
            raise RenderError(f"texture budget must be >= 0 bytes, got {budget_bytes}")
        self._gl = gl
        self._renderer_name = renderer_name
        self.budget_bytes = budget_bytes
        self._images: OrderedDict[str, GpuImage] = OrderedDict()
        self.nbytes = 0
        self.anisotropy = _max_anisotropy(gl) if anisotropic else 1.0

    def get(self, image: Image, call: int) -> int:
        """The GL texture of `image`, uploaded on first use."""
        got = self._images.get(image.key)
        if got is not None:
            got.used = call
            self._images.move_to_end(image.key)
            return got.texture
        need = image_bytes(image)
        if need > self.budget_bytes:
            h, w = image.pixels.shape[:2]
            raise RenderError(f"{image.source}: a {w}x{h} texture needs {need / 2**20:.1f} MiB on the GPU with its "
                              f"mipmaps, over the renderer's texture budget of {self.budget_bytes / 2**20:.0f} MiB")
        tex = self._upload(image)
        self._images[image.key] = GpuImage(tex, need, call)
        self.nbytes += need
        while self.nbytes > self.budget_bytes:
            key, oldest = next(iter(self._images.items()))
            if oldest.used == call:
                raise RenderError(f"{image.source}: the textures one frame draws need {self.nbytes / 2**20:.1f} MiB "
                                  f"on the GPU, over the renderer's texture budget of "
                                  f"{self.budget_bytes / 2**20:.0f} MiB")
            self._drop(key)
        return tex

    def _upload(self, image: Image) -> int:
        GL = self._gl
        px = np.ascontiguousarray(image.pixels, dtype=np.uint8)
        if px.ndim != 3 or px.shape[2] != 3 or px.shape[0] < 1 or px.shape[1] < 1:
            raise RenderError(f"{image.source}: a texture must be (h, w, 3) uint8, got {px.shape}")
        h, w = px.shape[:2]
        tex = GL.glGenTextures(1)
        GL.glActiveTexture(GL.GL_TEXTURE0 + UPLOAD_UNIT)
        GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        internal = GL.GL_SRGB8 if image.srgb else GL.GL_RGB8
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, internal, w, h, 0, GL.GL_RGB, GL.GL_UNSIGNED_BYTE, px)
        GL.glGenerateMipmap(GL.GL_TEXTURE_2D)
        for k, v in ((GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR_MIPMAP_LINEAR), (GL.GL_TEXTURE_MAG_FILTER, GL.GL_LINEAR),
                     (GL.GL_TEXTURE_WRAP_S, GL.GL_REPEAT), (GL.GL_TEXTURE_WRAP_T, GL.GL_REPEAT)):
            GL.glTexParameteri(GL.GL_TEXTURE_2D, k, v)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        return tex

    def _drop(self, key: str) -> None:
        got = self._images.pop(key)
        self.nbytes -= got.nbytes
        self._gl.glDeleteTextures([got.texture])

    def clear(self) -> None:
        for key in list(self._images):
            self._drop(key)

    def bind(self, material: Material, locs: dict[str, int], call: int) -> None:
        """Bind a material's images to MATERIAL_UNIT.. and set its uniforms in the program in use (its `locs`)."""
        GL = self._gl
        images = (material.base or WHITE, material.normal or FLAT, material.orm or ORM_ONE)
        textures = [self.get(image, call) for image in images]  # uploads first: an upload binds a unit of its own
        anisotropy = min(max(material.anisotropy, 1.0), self.anisotropy)
        for k, (name, image, tex) in enumerate(zip(("u_base_tex", "u_normal_tex", "u_orm_tex"), images, textures)):
            GL.glActiveTexture(GL.GL_TEXTURE0 + MATERIAL_UNIT + k)
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            got = self._images[image.key]
            if self.anisotropy > 1.0 and got.anisotropy != anisotropy:
                GL.glTexParameterf(GL.GL_TEXTURE_2D, GL_TEXTURE_MAX_ANISOTROPY, anisotropy)
                got.anisotropy = anisotropy
            if name in locs:
                GL.glUniform1i(locs[name], MATERIAL_UNIT + k)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        normal_scale = material.normal_scale if material.normal is not None else 0.0
        orm = material.orm is not None
        GL.glUniform4f(locs["u_material"], material.base_gain, normal_scale,
                       material.occlusion_strength if orm else 0.0, material.metallic_factor)
        if "u_triplanar_per_m" in locs:
            GL.glUniform1f(locs["u_triplanar_per_m"], material.triplanar_per_m)


GL_TEXTURE_MAX_ANISOTROPY = 0x84FE  # GL 4.6 core and EXT_texture_filter_anisotropic share the enum
GL_MAX_TEXTURE_MAX_ANISOTROPY = 0x84FF


def _max_anisotropy(GL) -> float:
    """The largest anisotropy the context allows, capped at MAX_ANISOTROPY; 1 where it has none."""
    n = int(GL.glGetIntegerv(GL.GL_NUM_EXTENSIONS))
    names = {GL.glGetStringi(GL.GL_EXTENSIONS, k).decode() for k in range(n)}
    if not names & {"GL_EXT_texture_filter_anisotropic", "GL_ARB_texture_filter_anisotropic"}:
        return 1.0
    return float(min(MAX_ANISOTROPY, float(GL.glGetFloatv(GL_MAX_TEXTURE_MAX_ANISOTROPY))))


def tangent_frames(vertices: np.ndarray, normals: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex tangents (n, 4) float32 for normal maps, glTF's TANGENT: xyz the unit direction of +u on the
    surface (orthogonal to the normal), w = +1 where the image's up (-v, rows towards the top) is normal x tangent,
    else -1. Accumulated from each face's dP/du and dP/dv weighted by its uv area (Lengyel's method); a vertex
    whose faces have no uv extent gets any unit vector orthogonal to its normal."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(uv, np.float64)
    f = np.asarray(faces, np.int64)
    n = np.asarray(normals, np.float64)
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    d1, d2 = t[f[:, 1]] - t[f[:, 0]], t[f[:, 2]] - t[f[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    # dP/du, dP/dv times det (sign kept, so each face counts with its uv area's orientation)
    sdir = e1 * d2[:, 1:2] - e2 * d1[:, 1:2]
    tdir = e2 * d1[:, 0:1] - e1 * d2[:, 0:1]
    sgn = np.sign(det)[:, None]
    corners = f.ravel()  # each face's contribution to its three vertices, summed per vertex (bincount, in order)
    tan = np.column_stack([np.bincount(corners, np.repeat(sdir[:, c] * sgn[:, 0], 3), len(v)) for c in range(3)])
    bit = np.column_stack([np.bincount(corners, np.repeat(tdir[:, c] * sgn[:, 0], 3), len(v)) for c in range(3)])
    nn = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    tan -= nn * np.sum(nn * tan, axis=1, keepdims=True)
    length = np.linalg.norm(tan, axis=1, keepdims=True)
    fallback = np.cross(nn, np.where(np.abs(nn[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    fallback /= np.maximum(np.linalg.norm(fallback, axis=1, keepdims=True), 1e-30)
    tan = np.where(length > 1e-12, tan / np.maximum(length, 1e-30), fallback)
    # the image's up is -v: w says whether normal x tangent points that way
    w = np.where(np.sum(np.cross(nn, tan) * -bit, axis=1) < 0.0, -1.0, 1.0)
    return np.column_stack([tan, w]).astype(np.float32)
