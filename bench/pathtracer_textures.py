"""Per-pixel materials in the path tracer: the renderer's textured surfaces (worker.render.materials) as one Mitsuba
BSDF written in Python, so a textured scene is path traced with the same textures, mapping and normal maps.

The BSDF is Lambertian with the renderer's albedo and normal per point:
    albedo = clamp(vertex albedo * base_gain * (1 - metallic) * base(uv) * scale + bias, 0, 1)
    normal = the interpolated vertex normal turned to the viewer's side, perturbed by the tangent-space normal map
             (`uv`: the mesh's tangents; `triplanar`: three object-frame projections blended by the normal's 4th power)
Images are sampled bilinearly at full resolution with repeat wrapping: the path tracer's many samples a pixel are
the filter (the renderer's mipmaps approximate that average). Light leaves a point only to the side it was seen
from (a surface is opaque); the cosine is taken to the perturbed normal, as the renderer does. Occlusion maps are
not modelled (they dim only the renderer's ambient and sky terms): a material with one is refused.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PTMaterial:
    """One textured surface. Images (h, w, 3) uint8 as the renderer uploads them, rows top first, texture coordinate
    (0, 0) at the top-left: `base` sRGB-encoded colour or None, `normal` the tangent-space normal map or None;
    `base_key`/`normal_key` name a procedural image (worker.scene.assets.textures) that can be made again from
    its name, so a stored scene holds its name and digest rather than its pixels (`procedural_image`).
    Per vertex (n = the mesh's vertex count), world frame: `normals` (n, 3); mapping "uv": `uv` (n, 2) and
    `tangents` (n, 4) (xyz the +u direction, w the handedness); mapping "triplanar": `obj_vertices` and
    `obj_normals` (n, 3) in the object frame and `normal_to_world` (3, 3)."""

    base: np.ndarray | None
    normal: np.ndarray | None
    base_gain: float
    normal_scale: float
    metallic: float
    mapping: str
    triplanar_per_m: float
    albedo_scale: np.ndarray
    albedo_bias: np.ndarray
    normals: np.ndarray
    uv: np.ndarray | None = None
    tangents: np.ndarray | None = None
    obj_vertices: np.ndarray | None = None
    obj_normals: np.ndarray | None = None
    normal_to_world: np.ndarray | None = None
    base_key: str | None = None
    normal_key: str | None = None


def srgb_to_linear(u8: np.ndarray) -> np.ndarray:
    """uint8 sRGB -> float32 linear (IEC 61966-2-1), as the renderer's sRGB textures decode before filtering."""
    x = np.asarray(u8, np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def from_render_material(material, item) -> PTMaterial:
    """The PTMaterial of a DrawItem drawn with `material` (a worker.render.Material)."""
    if material.orm is not None:
        raise ValueError(f"{material.orm.source}: occlusion/roughness/metal images are not path traced")
    mesh = item.mesh
    R = np.asarray(item.world_from_obj, np.float64)[:3, :3]
    to_world_n = np.linalg.inv(R).T
    normals = np.asarray(mesh.normals, np.float64) @ to_world_n.T

    if material.base is not None and not material.base.srgb:
        raise ValueError(f"{material.base.source}: a base colour image must be sRGB")

    def key(img):
        return img.key if img is not None and PROCEDURAL_KEY.fullmatch(img.key) else None

    common = {"base": None if material.base is None else material.base.pixels, "base_key": key(material.base),
              "normal": None if material.normal is None else material.normal.pixels,
              "normal_key": key(material.normal),
              "base_gain": float(material.base_gain), "normal_scale": float(material.normal_scale),
              "metallic": float(material.metallic_factor), "mapping": material.mapping,
              "triplanar_per_m": float(material.triplanar_per_m),
              "albedo_scale": np.asarray(item.albedo_scale, np.float32),
              "albedo_bias": np.asarray(item.albedo_bias, np.float32), "normals": normals.astype(np.float32)}
    if material.mapping == "uv":
        tangents = np.asarray(mesh.tangents, np.float64)
        return PTMaterial(**common, uv=np.asarray(mesh.uv, np.float32),
                          tangents=np.column_stack([tangents[:, :3] @ R.T, tangents[:, 3]]).astype(np.float32))
    return PTMaterial(**common, obj_vertices=np.asarray(mesh.vertices, np.float32),
                      obj_normals=np.asarray(mesh.normals, np.float32), normal_to_world=to_world_n)


PROCEDURAL_KEY = re.compile(r"texture/(\w+)/(\d+)/size=(\d+)/(albedo|normal)")


def procedural_image(key: str) -> np.ndarray:
    """The pixels of the procedural image named `key` (as worker.scene.materials names them), made again."""
    from seasynth.worker.scene.assets.textures import texture_set

    m = PROCEDURAL_KEY.fullmatch(key)
    if m is None:
        raise ValueError(f"{key!r} names no procedural image")
    ts = texture_set(m.group(1), int(m.group(2)), int(m.group(3)))
    return ts.albedo if m.group(4) == "albedo" else ts.normal


_REGISTERED: dict[str, type] = {}


def bsdf_class(mi):
    """The BSDF class for the active Mitsuba variant (defined once per variant)."""
    if mi.variant() in _REGISTERED:
        return _REGISTERED[mi.variant()]
    import drjit as dr

    def texture(image):
        return mi.Texture2f(mi.TensorXf(np.ascontiguousarray(image, np.float32)),
                            filter_mode=dr.FilterMode.Linear, wrap_mode=dr.WrapMode.Repeat)

    class Textured(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [self.m_flags]

        def setup(self, m: PTMaterial) -> Textured:
            self.m = m
            self.base = texture(srgb_to_linear(m.base)) if m.base is not None else None
            self.normal = texture(np.asarray(m.normal, np.float32) / 255.0) if m.normal is not None else None
            self.gain = m.base_gain * (1.0 - m.metallic)
            self.scale = mi.Color3f(*(float(x) for x in m.albedo_scale))
            self.bias = mi.Color3f(*(float(x) for x in m.albedo_bias))
            if m.mapping == "triplanar":
                self.n_to_world = mi.Matrix3f(np.asarray(m.normal_to_world, np.float32))
            return self

        def tap(self, tex, uv):
            v = tex.eval(uv)
            return mi.Vector3f(v[0], v[1], v[2])

        def unpack(self, t):
            s = self.m.normal_scale
            return mi.Vector3f((t.x * 2.0 - 1.0) * s, (t.y * 2.0 - 1.0) * s, t.z * 2.0 - 1.0)

        def shade(self, si, active):
            """(albedo, perturbed normal facing the viewer, geometric normal facing the viewer), world frame."""
            shape = si.shape
            wi = si.to_world(si.wi)
            ng = dr.select(dr.dot(wi, si.n) < 0.0, -si.n, si.n)
            nv = shape.eval_attribute_3("vertex_nrm", si, active)
            length = dr.norm(nv)
            N = dr.select(length > 1e-20, nv / dr.maximum(length, 1e-20), ng)
            side = dr.select(dr.dot(N, wi) < 0.0, -1.0, 1.0)
            base = mi.Vector3f(1.0)
            n = N
            if self.m.mapping == "uv":
                uv3 = shape.eval_attribute_3("vertex_uvw", si, active)
                uv = mi.Point2f(uv3.x, uv3.y)
                if self.base is not None:
                    base = self.tap(self.base, uv)
                if self.normal is not None:
                    t4 = shape.eval_attribute_3("vertex_tan", si, active)
                    sign = shape.eval_attribute_1("vertex_tsign", si, active)
                    T = t4 - N * dr.dot(N, t4)
                    tl = dr.norm(T)
                    T = T / dr.maximum(tl, 1e-12)
                    B = dr.cross(N, T) * dr.select(sign < 0.0, -1.0, 1.0)
                    m = self.unpack(self.tap(self.normal, uv))
                    n = dr.select((tl > 1e-12) & (length > 1e-20), dr.normalize(T * m.x + B * m.y + N * m.z), N)
            else:
                p = shape.eval_attribute_3("vertex_obj", si, active) * self.m.triplanar_per_m
                on = shape.eval_attribute_3("vertex_onrm", si, active)
                on = on / dr.maximum(dr.norm(on), 1e-20)
                w = mi.Vector3f(dr.abs(on.x), dr.abs(on.y), dr.abs(on.z))
                w = w * w * w * w
                w = w / dr.maximum(w.x + w.y + w.z, 1e-20)
                ux, uy, uz = mi.Point2f(p.z, p.y), mi.Point2f(p.x, p.z), mi.Point2f(p.x, p.y)
                if self.base is not None:
                    base = (w.x * self.tap(self.base, ux) + w.y * self.tap(self.base, uy)
                            + w.z * self.tap(self.base, uz))
                if self.normal is not None:
                    tx = self.unpack(self.tap(self.normal, ux))
                    ty = self.unpack(self.tap(self.normal, uy))
                    tz = self.unpack(self.tap(self.normal, uz))
                    # the maps' y points up the image (towards -t): flip it, then whiteout-blend as the renderer does
                    tx = mi.Vector3f(tx.x + on.z, -tx.y + on.y, dr.abs(tx.z) * on.x)
                    ty = mi.Vector3f(ty.x + on.x, -ty.y + on.z, dr.abs(ty.z) * on.y)
                    tz = mi.Vector3f(tz.x + on.x, -tz.y + on.y, dr.abs(tz.z) * on.z)
                    obj = dr.normalize(mi.Vector3f(tx.z, tx.y, tx.x) * w.x + mi.Vector3f(ty.x, ty.z, ty.y) * w.y
                                       + tz * w.z)
                    n = dr.select(length > 1e-20, dr.normalize(self.n_to_world @ obj), N)
            vc = shape.eval_attribute_3("vertex_color", si, active)
            albedo = dr.clip(mi.Color3f(vc.x * base.x, vc.y * base.y, vc.z * base.z) * self.gain * self.scale
                             + self.bias, 0.0, 1.0)
            return albedo, side * n, ng

        def eval_pdf(self, ctx, si, wo, active=True):
            albedo, n, ng = self.shade(si, active)
            w = si.to_world(wo)
            cos = dr.maximum(dr.dot(n, w), 0.0)
            ok = active & (dr.dot(w, ng) > 0.0)
            return dr.select(ok, albedo * (cos / dr.pi), 0.0), dr.select(active, cos / dr.pi, 0.0)

        def eval(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[1]

        def sample(self, ctx, si, sample1, sample2, active=True):
            albedo, n, ng = self.shade(si, active)
            local = mi.warp.square_to_cosine_hemisphere(sample2)
            w = mi.Frame3f(n).to_world(local)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = si.to_local(w)
            bs.pdf = local.z / dr.pi
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = mi.UInt32(0)
            ok = active & (local.z > 0.0) & (dr.dot(w, ng) > 0.0)
            return bs, dr.select(ok, albedo, 0.0)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"SeasynthTextured[{self.m.mapping}]"

    mi.register_bsdf("seasynth_textured", lambda props: Textured(props))
    _REGISTERED[mi.variant()] = Textured
    return Textured


def textured_mesh(mesh, name: str, mi):
    """An mi.Mesh of `mesh` (a pathtracer.PTMesh whose `material` is set) with the textured BSDF and the vertex
    attributes it reads; Mitsuba's own vertex normals are left for its shading frame."""
    m: PTMaterial = mesh.material
    cls = bsdf_class(mi)
    props = mi.Properties()
    props["bsdf"] = cls(mi.Properties()).setup(m)
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    out = mi.Mesh(name, len(vertices), len(faces), props, has_vertex_normals=True)

    def attr(key, values, channels):
        out.add_attribute(key, channels, mi.Float(np.ascontiguousarray(values, np.float32).ravel()))

    attr("vertex_color", mesh.albedo, 3)
    attr("vertex_nrm", m.normals, 3)
    if m.mapping == "uv":
        attr("vertex_uvw", np.column_stack([m.uv, np.zeros(len(vertices))]), 3)
        attr("vertex_tan", m.tangents[:, :3], 3)
        attr("vertex_tsign", m.tangents[:, 3], 1)
    else:
        attr("vertex_obj", m.obj_vertices, 3)
        attr("vertex_onrm", m.obj_normals, 3)
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return out
