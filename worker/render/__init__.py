"""Rendering: the Renderer protocol, what a frame asks of it, and what it returns."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class View:
    """A pinhole camera. Camera frame is KITTI's: x right, y down, z forward (metres)."""

    K: np.ndarray  # (3, 3) float64, pixels; pixel centres at integer coordinates
    width: int
    height: int
    cam_from_world: np.ndarray  # (4, 4) float64
    near: float  # metres
    far: float  # metres


def ray_norms(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h, w) float32: |K^-1 [u, v, 1]| per pixel centre, so range = z_depth * ray_norm."""
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2).astype(np.float32)


def normal_matrix(linear: np.ndarray) -> np.ndarray:
    """(3, 3) float32: the inverse transpose of an object's (3, 3) linear map (its rotation times its scale), which
    takes its normals to the camera's, up to the positive factor the shader normalises away. The map and its inverse
    are scaled by a power of two (exact: the shaded normal keeps every bit) into float32's range where an object's
    scale (targets.scale down to 5e-324) takes them out of it; a map scaled to nothing (singular) takes the identity,
    as its object covers no pixel."""
    try:
        nrm = np.linalg.inv(_near_one(np.asarray(linear, np.float64))).T
    except np.linalg.LinAlgError:
        return np.eye(3, dtype=np.float32)
    return _near_one(nrm).astype(np.float32) if np.all(np.isfinite(nrm)) else np.eye(3, dtype=np.float32)


def _near_one(m: np.ndarray) -> np.ndarray:
    """m, or m times the power of two that brings its largest entry to [0.5, 1) where that lies outside 2^+-60."""
    top = float(np.max(np.abs(m)))
    exponent = int(np.frexp(top)[1]) if np.isfinite(top) and top > 0 else 0
    return np.ldexp(m, -exponent) if abs(exponent) > 60 else m


@dataclass(frozen=True, eq=False)
class Image:
    """A texture image, uploaded once per process under `key` (with its mipmaps)."""

    key: str
    pixels: np.ndarray  # (h, w, 3) uint8, rows top first; texture coordinate (0, 0) is the top-left corner
    srgb: bool  # colour (sRGB-encoded, decoded to linear when sampled) or data (normals, occlusion/roughness/metal)
    source: str  # the file or procedural family it came from, named in errors


@dataclass(frozen=True)
class Material:
    """What a textured surface adds per pixel (worker.render.materials): a mesh without one is vertex-coloured.

    The albedo at a pixel is clamp(vertex albedo * base_gain * base(uv) * (1 - metallic) * scale + bias, 0, 1)
    (scale and bias: the DrawItem's); the normal is the vertex normal perturbed by the tangent-space normal map
    (xy times normal_scale, glTF's convention); occlusion (orm's red, 1 + occlusion_strength (r - 1)) dims the
    ambient and sky light only; metallic = metallic_factor * orm's blue. The shading is diffuse, so roughness
    (orm's green) has nothing to change and is not read.

    mapping "uv": the mesh's texture coordinates and tangents (Mesh.uv, Mesh.tangents). "triplanar": no texture
    coordinates; three planar projections of the object frame (triplanar_per_m texture repeats per metre) blended
    by the normal, for procedural meshes that have no unwrapping.
    """

    base: Image | None = None
    base_gain: float = 1.0
    normal: Image | None = None
    normal_scale: float = 1.0
    orm: Image | None = None
    occlusion_strength: float = 1.0
    metallic_factor: float = 0.0
    mapping: str = "uv"
    triplanar_per_m: float = 1.0
    anisotropy: float = 16.0  # the anisotropic filter's most taps (1: trilinear), within what the renderer allows

    def images(self) -> tuple[Image, ...]:
        return tuple(i for i in (self.base, self.normal, self.orm) if i is not None)


@dataclass(frozen=True)
class Mesh:
    """Geometry uploaded once per process under `key`."""

    key: str
    vertices: np.ndarray  # (n, 3) float32, metres, object frame
    normals: np.ndarray  # (n, 3) float32, unit (or zero for degenerate vertices)
    albedo: np.ndarray  # (n, 3) float32, linear RGB in [0, 1]
    faces: np.ndarray  # (m, 3) uint32
    radius: float  # metres: every vertex lies within this distance of `centre`
    centre: np.ndarray  # (3,) float64, object frame
    material: Material | None = None  # per-pixel textures; None: vertex colours only
    # Meshes with several materials (a user's glTF or OBJ): (first face, face count, material or None) ranges that
    # cover the faces in order; the surface pass draws each range with its material (`material` is then unused),
    # every other pass the whole mesh at once.
    groups: tuple[tuple[int, int, Material | None], ...] = ()
    uv: np.ndarray | None = None  # (n, 2) float32 texture coordinates (material mapping "uv")
    tangents: np.ndarray | None = None  # (n, 4) float32: unit tangent along +u, w = +-1 (glTF's TANGENT)


@dataclass(frozen=True)
class DrawItem:
    """One placed instance of an uploaded mesh."""

    mesh: Mesh
    world_from_obj: np.ndarray  # (4, 4) float64
    albedo_scale: np.ndarray  # (3,) float32
    albedo_bias: np.ndarray  # (3,) float32
    instance_id: int  # 0 = terrain (unlabelled), else 1..65535
    casts_shadows: bool = True  # False: left out of the shadow maps (the far seabed: it shadows nothing drawn)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """(centre (3,) float64 world metres, radius metres) holding every vertex as placed."""
        M = self.world_from_obj
        scale = float(np.abs(np.linalg.svd(M[:3, :3], compute_uv=False)).max())
        return M[:3, :3] @ self.mesh.centre + M[:3, 3], self.mesh.radius * scale

    def world_vertices(self) -> np.ndarray:
        """(V, 3) float64: the mesh's vertices as placed, world metres."""
        M = self.world_from_obj
        return self.mesh.vertices.astype(np.float64) @ M[:3, :3].T + M[:3, 3]

    def shaded_albedo(self) -> np.ndarray:
        """(V, 3): each vertex's albedo as the surface shader takes it, clamp(albedo * scale + bias, 0, 1)."""
        return np.clip(self.mesh.albedo * self.albedo_scale + self.albedo_bias, 0.0, 1.0)


@dataclass(frozen=True)
class Lighting:
    sun_dir_world: np.ndarray  # (3,) float64, unit vector towards the sun
    sun_intensity: float
    ambient: float


@dataclass(frozen=True)
class WaterParams:
    """Per-channel coefficients of the image formation model (linear RGB)."""

    beta_D: np.ndarray  # (3,) float64, 1/m
    beta_B: np.ndarray  # (3,) float64, 1/m
    B_inf: np.ndarray  # (3,) float64, linear RGB


@dataclass(frozen=True)
class Sampling:
    """How many samples make one output pixel: supersample^2 pixels, each with `msaa` coverage samples."""

    msaa: int = 4
    supersample: int = 1
    # Shade every sample at its own position (range, J) instead of once per pixel at the pixel centre.
    per_sample_shading: bool = True

    @property
    def per_pixel(self) -> int:
        return self.msaa * self.supersample**2


@dataclass(frozen=True)
class Passes:
    """What to render. A pass nobody asked for is never drawn or read back."""

    clean: bool = False  # the in-air image J, resolved like the hazed one
    ids: bool = False  # per-pixel instance ids at pixel centres
    # Per-pixel range: +inf exactly where no sample of the pixel hits a surface (the pixel is pure water); else
    # the range at the pixel centre where it hits a surface, else the nearest of the pixel's samples that does.
    range: bool = False
    # The image as exact 8-bit sRGB codes ((h, w, 3) uint8, equal to srgb.encode_srgb8 of the float image),
    # encoded on the GPU and read back at a quarter of the bytes. For frames whose image needs nothing more in float.
    srgb8: bool = False


@dataclass(frozen=True)
class RenderResult:
    image: np.ndarray  # (h, w, 3) float32 linear RGB, hazed when water was given (uint8 sRGB codes: Passes.srgb8)
    clean: np.ndarray | None  # (h, w, 3) float32 linear RGB in air
    instance: np.ndarray | None  # (h, w) uint32, 0 = terrain or open water
    range_m: np.ndarray | None  # (h, w) float32 metres (see Passes.range), +inf where no sample hits a surface
    # What ran, in order: GL passes drawn ("surface[+range]", "resolve[+haze]", "ids", "ids+range", "range") and
    # attachments read back ("read image", "read clean", "read nearest range", "read ids", "read range"). For tests
    # and benchmarks; outputs never depend on it.
    passes: tuple[str, ...] = ()


class Renderer(Protocol):
    """A renderer backend. One per process, reused across frames; close() releases its resources."""

    name: str  # the GL renderer string, recorded with every frame

    def render(
        self,
        view: View,
        items: list[DrawItem],
        lighting: Lighting,
        water: WaterParams | None,
        sampling: Sampling,
        passes: Passes,
        mark: Callable[[str], None] | None = None,
    ) -> RenderResult: ...

    def pixels_alone(self, view: View, item: DrawItem, region: tuple[int, int, int, int] | None = None) -> int: ...

    def pixels_alone_many(
        self, view: View, jobs: list[tuple[DrawItem, tuple[int, int, int, int] | None]]
    ) -> list[int]: ...

    def samples(
        self, view: View, items: list[DrawItem], lighting: Lighting, sampling: Sampling
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def close(self) -> None: ...
