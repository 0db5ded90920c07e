"""The materials of a scene's surfaces (seasynth.worker.render.Material): seeded procedural texture sets on the
built-in terrains and procedural assets (seasynth.worker.scene.assets.textures), a user's texture set on the
terrain, and the texture coordinates of a terrain's vertices."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.frame.srgb import decode_srgb8
from seasynth.worker.render import Image, Material
from seasynth.worker.scene.assets import Asset, UserSurface
from seasynth.worker.scene.assets.procedural import stable_seed
from seasynth.worker.scene.assets.terrain import Texture, value_noise
from seasynth.worker.scene.assets.textures import normal_map
from seasynth.worker.scene.texture_cache import shared_texture_set

# The texture family of each procedural asset kind and terrain style.
ASSET_FAMILY = {"urchin": "urchin", "rock": "stone", "coral": "coral", "seaweed": "seaweed", "clam": "clam",
                # animals: ossicles and papillae read as tubercles, sponges have pores, scales as fine growth lines
                "starfish": "urchin", "sea_cucumber": "urchin", "scallop": "clam", "anemone": "seaweed",
                "sponge": "coral", "fish": "clam",
                # litter: silted smooth surfaces (mud: a 1 m tile, so a bottle sees its gentle mottling), fibres,
                # weathered concrete and rubber
                "plastic_bottle": "mud", "glass_bottle": "mud", "can": "mud", "tyre": "stone", "rope": "seaweed",
                "net": "seaweed", "cinder_block": "stone", "pipe": "mud"}
STYLE_FAMILY = {"sand": "sand", "pebbles": "pebbles", "rock": "rock"}


@functools.lru_cache(maxsize=256)
def procedural_material(family: str, variant: int, size: int, mapping: str, anisotropy: float = 16.0) -> Material:
    """A procedural texture set as a material: its albedo factor as the base colour (base_gain scales it so its mean
    is 1: the surface keeps its colour and gains detail) and its normal map; triplanar mappings repeat it every
    set's tile_m."""
    ts = shared_texture_set(family, variant, size)
    return Material(base=Image(f"{ts.key}/albedo", ts.albedo, True, ts.source), base_gain=ts.albedo_gain,
                    normal=Image(f"{ts.key}/normal", ts.normal, False, ts.source), mapping=mapping,
                    triplanar_per_m=1.0 / ts.tile_m, anisotropy=anisotropy)


def texture_variant(variant: int | None, spec: DatasetSpec) -> int:
    """The texture variant of an asset or terrain variant (one texture per variant, cycling through
    materials.variants)."""
    return (variant or 0) % spec.materials.variants


def asset_material(asset: Asset, variant: int | None, spec: DatasetSpec) -> Material | None:
    """The material of a procedural asset (triplanar: their meshes have no unwrapping), None for user files (their
    own materials come with their meshes) or with materials.procedural off."""
    if not spec.materials.procedural or not asset.key.startswith("procedural/"):
        return None
    kind = asset.key.split("/")[1]
    m = spec.materials
    return procedural_material(ASSET_FAMILY[kind], texture_variant(variant, spec), m.texture_px, "triplanar",
                               float(m.anisotropy))


def user_surface(asset: Asset, spec: DatasetSpec) -> UserSurface | None:
    """A user mesh's own materials, filtered with the spec's materials.anisotropy like every texture (None: the
    mesh has no texture)."""
    surface = asset.surface
    if surface is None:
        return None
    anisotropy = float(spec.materials.anisotropy)
    key = (asset.key, anisotropy)
    got = _user_surfaces.get(key)
    if got is None or got[0] is not surface:
        groups = tuple((first, count, None if m is None else dataclasses.replace(m, anisotropy=anisotropy))
                       for first, count, m in surface.groups)
        got = _user_surfaces[key] = (surface, UserSurface(uv=surface.uv, groups=groups))
        while len(_user_surfaces) > 64:
            _user_surfaces.pop(next(iter(_user_surfaces)))
    return got[1]


_user_surfaces: dict[tuple[str, float], tuple[UserSurface, UserSurface]] = {}  # (asset key, anisotropy) -> (its, ours)


def style_material(style: str, variant: int, spec: DatasetSpec) -> Material | None:
    """The procedural material of a built-in terrain style's variant; None with materials.procedural off."""
    if not spec.materials.procedural:
        return None
    m = spec.materials
    return procedural_material(STYLE_FAMILY[style], texture_variant(variant, spec), m.texture_px, "uv",
                               float(m.anisotropy))


@functools.lru_cache(maxsize=16)
def user_material(albedo: Texture, normal: Texture | None, height: Texture | None, height_m: float, tile_m: float,
                  anisotropy: float = 16.0) -> Material:
    """A user's terrain texture set: the albedo image as the base colour (the surface's own colour is replaced:
    terrains with one are drawn white), the normal map as given or made from the height map (grey levels spanning
    height_m metres over a tile of tile_m)."""
    normal_image = None
    if normal is not None:
        normal_image = Image(f"file/{normal.sha256}/normal", normal.pixels, False, normal.source)
    elif height is not None:
        grey = height.pixels.astype(np.float64).mean(axis=2) / 255.0 * height_m
        h, w = grey.shape  # the image spans tile_m both ways: columns tile_m / w apart, rows tile_m / h
        normal_image = Image(f"file/{height.sha256}/height/{height_m!r}/{tile_m!r}",
                             normal_map(grey - grey.mean(), tile_m / w, tile_m / h), False, height.source)
    return Material(base=Image(f"file/{albedo.sha256}/albedo", albedo.pixels, True, albedo.source),
                    normal=normal_image, mapping="uv", anisotropy=anisotropy)


def material_key(material: Material | None) -> str:
    """What names a material's look: its images' keys and its factors (GPU meshes are keyed with it)."""
    if material is None:
        return "none"
    images = ",".join(i.key for i in material.images())
    return (f"{material.mapping}/{images}/{material.base_gain!r}/{material.normal_scale!r}/"
            f"{material.triplanar_per_m!r}/aniso={material.anisotropy!r}")


def terrain_tile_m(material: Material | None, spec: DatasetSpec) -> float:
    """Metres one texture repeat spans on the terrain: the procedural set's own size, else texture_tile_m."""
    if material is not None and spec.terrain.texture is None and material.base is not None:
        return 1.0 / material.triplanar_per_m
    return spec.terrain.texture_tile_m


# Anti-tiling: texture coordinates displaced by a smooth noise up to WARP_REPEATS of a repeat, its features
# 1 / WARP_FREQUENCY repeats apart, so repeats no longer line up in a grid. Its largest slope (0.137 over 20,000
# random points and four directions) stretches or squeezes a texture by under 15% anywhere. It costs the renderer nothing: the
# warp is in the vertices' texture coordinates (the terrain's 6 cm grid resolves it; the far field's rings
# interpolate it linearly, far away).
WARP_REPEATS = 0.3
WARP_FREQUENCY = 0.125


def uv_warp(xy_repeats: np.ndarray) -> np.ndarray:
    """(n, 2) float64 displacement of texture coordinates (in repeats) at positions (n, 2) in repeats: two value
    noises of their own seeds, a function of the position alone (the tile and every far-field ring agree)."""
    out = np.empty_like(xy_repeats)
    for k in range(2):
        rng = np.random.default_rng(np.random.SeedSequence([stable_seed("terrain-uv-warp"), k]))
        out[:, k] = WARP_REPEATS * value_noise(rng, xy_repeats, WARP_FREQUENCY)
    return out


def terrain_uv(vertices: np.ndarray, tile_m: float, warp: bool = True) -> np.ndarray:
    """(n, 2) float32 texture coordinates of terrain vertices: world x along u, world y up the image (-v), one
    repeat every tile_m metres; warp: displaced by uv_warp (terrain.anti_tiling)."""
    v = np.asarray(vertices, np.float64)
    uv = np.column_stack([v[:, 0] / tile_m, -v[:, 1] / tile_m])
    if warp:
        uv = uv + uv_warp(uv)
    return uv.astype(np.float32)


@functools.lru_cache(maxsize=32)
def albedo_factor(material: Material | None) -> np.ndarray:
    """(3,) float64 what a material's maps multiply a surface's vertex albedo by on average (linear light), as the
    surface shader forms it (`render.materials.textured_albedo`): the base map (decoded) x base_gain x (1 -
    metallic_factor x the orm map's blue) x the occlusion (1 + occlusion_strength (orm red - 1)), each averaged over
    its texels on its own, x the mean of the normal map's normals along the surface's own normal (what a Lambertian
    surface's mean shading keeps of the light, irradiance being linear in the normal; the shader's `spread` is this
    over a footprint). Ones without a material."""
    if material is None:
        return np.ones(3)
    out = np.full(3, float(material.base_gain))
    if material.base is not None:
        out = out * decode_srgb8(material.base.pixels.reshape(-1, 3), np.float64).mean(axis=0)
    if material.orm is not None:
        orm = material.orm.pixels.reshape(-1, 3).astype(np.float64) / 255.0
        out = out * (1.0 - material.metallic_factor * orm[:, 2].mean())
        out = out * (1.0 + material.occlusion_strength * (orm[:, 0].mean() - 1.0))
    if material.normal is not None:
        m = material.normal.pixels.reshape(-1, 3).astype(np.float64) / 255.0 * 2.0 - 1.0
        m[:, :2] *= material.normal_scale
        out = out * float(np.mean(np.maximum(m[:, 2], 0.0) / np.maximum(np.linalg.norm(m, axis=1), 1e-12)))
    return out
