"""Per-pixel materials of user meshes: a glTF's metallic-roughness materials and an OBJ's MTL texture maps read as
seasynth.worker.render.Material, with each part's texture coordinates and vertex colours, for the mesh loader
(seasynth.worker.scene.assets.user).

What is read. glTF 2.0: baseColorTexture (sRGB) with baseColorFactor (multiplied into the part's vertex colours:
COLOR_0 where given, as trimesh reports it, else white), normalTexture with its scale, occlusionTexture (red) with
its strength and metallicRoughnessTexture (blue: metal) packed into one occlusion/roughness/metal image, and
metallicFactor (1 where absent, as glTF says: such a surface is a metal, which the diffuse shading draws dark).
OBJ/MTL: map_Kd (the base colour), Kd (multiplied into the vertex colours, 1 where absent), map_Bump or bump with
an optional `-bm s`: an image whose mean colour is bluish (blue > 0.7, red and green within 0.1 of 0.5) is a
tangent-space normal map (s its normal_scale), any other a height map whose grey level (0..1, the mean of red,
green and blue) times s is the height in texel widths (s = 1: one texel's rise per texel from black to white).
Not read: alpha (alphaMode, alphaCutoff and the base colour's alpha: surfaces are opaque), roughness (the shading
is diffuse), emissive, texCoord other than 0, texture transforms and samplers (textures repeat, filtered
trilinearly), and the MTL's other maps and map options (-o, -s, ...).

Factors are linear: vertex colours are sRGB-encoded, so each is decoded, multiplied and encoded again.
"""

from __future__ import annotations

import hashlib
import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from seasynth.service.errors import AssetError
from seasynth.service.mtl import MtlMaterial, read_mtl
from seasynth.service.textures import PixelBudget
from seasynth.worker.frame.srgb import decode_srgb8, encode_srgb8
from seasynth.worker.render import Image, Material
from seasynth.worker.scene.assets.textures import normal_map

# trimesh is handed the glTF with material i named MATERIAL_NAME + i: its parts then say which material they have.
MATERIAL_NAME = "seasynth-material:"
GLB_HEADER = struct.Struct("<4sII")  # magic, version, length
GLB_CHUNK = struct.Struct("<I4s")  # length, type
WHITE = np.array([255, 255, 255, 255], np.uint8)
NORMAL_MAP_BLUE = 0.7  # an OBJ bump image is a normal map if its mean blue is above this...
NORMAL_MAP_RG = 0.1  # ...and its mean red and green lie within this of 0.5


@dataclass(frozen=True)
class PartSurface:
    """What one textured part of a user mesh draws with."""

    colours: np.ndarray  # (n, 4) uint8 sRGB-encoded vertex colours, the base colour's factor in them
    uv: np.ndarray  # (n, 2) float64 texture coordinates, (0, 0) the image's top-left
    material: Material
    group: int  # the material's index in its file: parts of one material share it


def flip_v(uv: np.ndarray | None, n: int, where: str = "a textured part") -> np.ndarray:
    """trimesh's texture coordinates ((0, 0) bottom-left: it flips glTF's v, keeps OBJ's) -> the renderer's
    ((0, 0) the image's top-left); AssetError naming `where` if a textured part has none for its n vertices (it
    would draw one texel's colour everywhere)."""
    if uv is None or len(uv) != n:
        have = "none" if uv is None else f"{len(uv)} for {n} vertices"
        raise AssetError(f"{where}: has textures but no texture coordinates ({have})")
    uv = np.asarray(uv, np.float64)
    return np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])


def scaled_colours(colours: np.ndarray, factor) -> np.ndarray:
    """(n, 4) uint8 sRGB-encoded colours times a linear (3,) factor, alpha kept."""
    out = np.array(colours, np.uint8)
    out[:, :3] = encode_srgb8(decode_srgb8(out[:, :3], np.float64) * np.asarray(factor, np.float64)[:3])
    return out


def decode_image(image, label: str, budget: PixelBudget) -> np.ndarray:
    """A PIL image (opened, not yet decoded) counted into `budget` and decoded: (h, w, 3) uint8, alpha dropped;
    AssetError naming `label` if it does not decode."""
    budget.add(label, image.size)
    try:
        return np.array(image.convert("RGB"), np.uint8)
    except Exception as exc:  # any decoder failure is a bad image: re-raised naming it
        raise AssetError(f"{label}: cannot decode the image ({type(exc).__name__}: {exc})") from exc


def image_key(sha256: str, index: int, kind: str, pixels: np.ndarray) -> str:
    """GPU key of a user texture: the mesh file's digest, the material's index, what the image is for, and a digest
    of its pixels (a glTF's or OBJ's image files are not in the mesh file's digest)."""
    return f"file/{sha256}/{index}/{kind}/{hashlib.sha256(pixels.tobytes()).hexdigest()[:16]}"


def orm_pixels(occlusion: np.ndarray | None, metal_rough: np.ndarray | None) -> np.ndarray:
    """(h, w, 3) uint8 occlusion (red), roughness (green), metal (blue) from an occlusion image (its red) and a
    metallic-roughness one (its green and blue), resized (bilinear) to the larger of their sizes; 255 where absent."""
    from PIL import Image as PILImage

    given = [a for a in (occlusion, metal_rough) if a is not None]
    h, w = max(a.shape[0] for a in given), max(a.shape[1] for a in given)

    def sized(a: np.ndarray) -> np.ndarray:
        if a.shape[:2] == (h, w):
            return a
        return np.asarray(PILImage.fromarray(a).resize((w, h), PILImage.BILINEAR))

    out = np.full((h, w, 3), 255, np.uint8)
    if occlusion is not None:
        out[..., 0] = sized(occlusion)[..., 0]
    if metal_rough is not None:
        out[..., 1:] = sized(metal_rough)[..., 1:]
    return out


# ---- glTF -------------------------------------------------------------------------------------------------------
def glb_chunks(data: bytes, where: str) -> list[tuple[bytes, bytes]]:
    """(type, payload) of every chunk of a binary glTF."""
    if len(data) < GLB_HEADER.size or data[:4] != b"glTF":
        raise AssetError(f"{where}: not a valid glb mesh (no glTF binary header)")
    _, version, length = GLB_HEADER.unpack_from(data)
    if version != 2:
        raise AssetError(f"{where}: not a valid glb mesh (version {version}; glTF 2.0 is read)")
    chunks, offset = [], GLB_HEADER.size
    while offset + GLB_CHUNK.size <= min(length, len(data)):
        size, kind = GLB_CHUNK.unpack_from(data, offset)
        chunks.append((kind, data[offset + GLB_CHUNK.size:offset + GLB_CHUNK.size + size]))
        offset += GLB_CHUNK.size + size
    return chunks


def gltf_tree(data: bytes, kind: str, where: str) -> dict[str, Any]:
    """The JSON tree of a glTF (kind "gltf") or binary glTF ("glb")."""
    text = data if kind == "gltf" else next((c for k, c in glb_chunks(data, where) if k == b"JSON"), None)
    if text is None:
        raise AssetError(f"{where}: not a valid glb mesh (no JSON chunk)")
    try:
        tree = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise AssetError(f"{where}: not a valid {kind} mesh (its JSON does not parse: {type(exc).__name__})") from None
    if not isinstance(tree, dict):
        raise AssetError(f"{where}: not a valid {kind} mesh (its JSON is not an object)")
    return tree


def with_tree(data: bytes, kind: str, tree: dict[str, Any], where: str) -> bytes:
    """The glTF's bytes with its JSON replaced by `tree` (a binary glTF keeps its other chunks)."""
    text = json.dumps(tree).encode()
    if kind == "gltf":
        return text
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned; JSON pads with spaces
    chunks = [(k, text if k == b"JSON" else c) for k, c in glb_chunks(data, where)]
    body = b"".join(GLB_CHUNK.pack(len(c), k) + c for k, c in chunks)
    return GLB_HEADER.pack(b"glTF", 2, GLB_HEADER.size + len(body)) + body


TEXTURE_FIELDS = (("base", "baseColorTexture", True), ("metal_rough", "metallicRoughnessTexture", True),
                  ("normal", "normalTexture", False), ("occlusion", "occlusionTexture", False))


def texture_info(material: dict[str, Any], field: str, in_pbr: bool) -> dict[str, Any] | None:
    holder = (material.get("pbrMetallicRoughness") or {}) if in_pbr else material
    return holder.get(field)


class GltfSurfaces:
    """The textured materials of one glTF, built on first use by the parts that have them."""

    def __init__(self, path: Path, kind: str, where: str, name: str, sha256: str, data: bytes,
                 tree: dict[str, Any]) -> None:
        self.path, self.kind, self.where, self.name, self.sha256 = path, kind, where, name, sha256
        self.data, self.tree = data, tree
        self.budget = PixelBudget(where)
        self._materials: dict[int, Material | None] = {}
        self._pixels: dict[int | str, np.ndarray] = {}  # by image index

    def load_scene(self) -> trimesh.Scene:
        tree = dict(self.tree)
        tree["materials"] = [{**m, "name": f"{MATERIAL_NAME}{i}"} for i, m in enumerate(tree["materials"])]
        return trimesh.load_scene(io.BytesIO(with_tree(self.data, self.kind, tree, self.where)), file_type=self.kind,
                                  resolver=trimesh.resolvers.FilePathResolver(str(self.path)))

    def part(self, mesh: trimesh.Trimesh) -> PartSurface | None:
        """The part's surface, None if its material has no texture (it keeps its vertex colours)."""
        pbr = getattr(mesh.visual, "material", None)
        name = getattr(pbr, "name", None)
        if not isinstance(name, str) or not name.startswith(MATERIAL_NAME):
            return None
        index = int(name[len(MATERIAL_NAME):])
        if index not in self._materials:
            self._materials[index] = self._material(index, pbr)
        material = self._materials[index]
        if material is None:
            return None
        spec = self.tree["materials"][index]
        factor = (spec.get("pbrMetallicRoughness") or {}).get("baseColorFactor", [1.0, 1.0, 1.0, 1.0])
        n = len(mesh.vertices)
        colour = mesh.visual.vertex_attributes.get("color")
        base = np.tile(WHITE, (n, 1)) if colour is None or len(colour) != n else trimesh.visual.color.to_rgba(colour)
        uv = flip_v(mesh.visual.uv, n, f"{self.path.name}: material {index}")
        return PartSurface(scaled_colours(base, [float(f) for f in factor[:3]]), uv, material, index)

    def _material(self, index: int, pbr) -> Material | None:
        spec = self.tree["materials"][index]
        label = f"material {index}" + (f" ({spec['name']!r})" if isinstance(spec.get("name"), str) else "")
        loaded = {"base": pbr.baseColorTexture, "metal_rough": pbr.metallicRoughnessTexture,
                  "normal": pbr.normalTexture, "occlusion": pbr.occlusionTexture}
        px: dict[str, np.ndarray | None] = {}
        for kind, field, in_pbr in TEXTURE_FIELDS:
            info = texture_info(spec, field, in_pbr)
            px[kind] = None if info is None else self._image(info, loaded[kind], f"{label}'s {field}")
        if all(p is None for p in px.values()):
            return None
        normal = spec.get("normalTexture") or {}
        occlusion = spec.get("occlusionTexture") or {}
        pbr_spec = spec.get("pbrMetallicRoughness") or {}
        base = normal_image = orm = None
        if px["base"] is not None:
            base = Image(image_key(self.sha256, index, "base", px["base"]), px["base"], True,
                         f"{self.name}: {label}'s base colour")
        if px["normal"] is not None:
            normal_image = Image(image_key(self.sha256, index, "normal", px["normal"]), px["normal"], False,
                                 f"{self.name}: {label}'s normal map")
        if px["occlusion"] is not None or px["metal_rough"] is not None:
            orm_px = orm_pixels(px["occlusion"], px["metal_rough"])
            orm = Image(image_key(self.sha256, index, "orm", orm_px), orm_px, False,
                        f"{self.name}: {label}'s occlusion and metallic-roughness")
        return Material(base=base, normal=normal_image, normal_scale=float(normal.get("scale", 1.0)), orm=orm,
                        occlusion_strength=float(occlusion.get("strength", 1.0)),
                        metallic_factor=float(pbr_spec.get("metallicFactor", 1.0)))

    def _image(self, info: dict[str, Any], image, what: str) -> np.ndarray:
        """The pixels of the image a texture info names; AssetError naming the file and the image if trimesh could
        not open it or it does not decode."""
        source = self.tree["textures"][info["index"]].get("source")
        images = self.tree.get("images", [])
        spec = images[source] if isinstance(source, int) and 0 <= source < len(images) else {}
        uri = spec.get("uri", "")
        named = f" ({uri!r})" if uri and not uri.startswith("data:") else ""
        label = f"{self.where}: image {source}{named}"
        if image is None:
            raise AssetError(f"{label}, {what}, cannot be read as an image")
        key = source if isinstance(source, int) else f"texture {info['index']}"  # e.g. EXT_texture_webp's source
        if key not in self._pixels:
            self._pixels[key] = decode_image(image, label, self.budget)
        return self._pixels[key]


# ---- OBJ / MTL --------------------------------------------------------------------------------------------------
def mtl_library(obj: Path, where: str) -> tuple[dict[str, MtlMaterial], Path | None]:
    """The OBJ's material library (the rest of the first line holding `mtllib`, as trimesh reads it) and its path;
    ({}, None) if it names none or the file is missing (trimesh loads such an OBJ uncoloured)."""
    text = obj.read_bytes().decode("utf-8", "replace")
    at = text.find("mtllib")
    if at < 0:
        return {}, None
    ref = text[at + 6:text.find("\n", at) if "\n" in text[at:] else len(text)].strip()
    path = resolve_beside(obj, ref)
    if path is None:
        return {}, None
    return read_mtl(path.read_bytes().decode("utf-8", "replace"), f"{where}: {ref}"), path


def resolve_beside(mesh: Path, ref: str) -> Path | None:
    """A file an OBJ or its MTL names, as trimesh finds it: beside the mesh, else by its last component there."""
    for candidate in (mesh.parent / ref, mesh.parent / Path(ref.replace("\\", "/")).name):
        if ref and candidate.is_file():
            return candidate
    return None


class ObjSurfaces:
    """The textured materials of one OBJ's MTL library, built on first use by the parts that have them."""

    def __init__(self, path: Path, where: str, name: str, sha256: str, library: dict[str, MtlMaterial], mtl: Path
                 ) -> None:
        self.path, self.where, self.sha256, self.library = path, where, sha256, library
        self.mtl_where, self.mtl_name = f"{where}: {mtl.name}", f"{name}: {mtl.name}"
        self.budget = PixelBudget(where)
        self._materials: dict[int, Material] = {}
        self._pixels: dict[Path, np.ndarray] = {}

    def load_scene(self) -> trimesh.Scene:
        return trimesh.load_scene(str(self.path), file_type="obj")

    def part(self, mesh: trimesh.Trimesh) -> PartSurface | None:
        """The part's surface, None if its material has no map (it keeps its vertex colours)."""
        entry = self.library.get(getattr(getattr(mesh.visual, "material", None), "name", None))
        if entry is None or (entry.map_kd is None and entry.bump is None):
            return None
        if entry.index not in self._materials:
            self._materials[entry.index] = self._material(entry)
        n = len(mesh.vertices)
        kd = entry.kd if entry.kd is not None and len(entry.kd) == 3 else (1.0, 1.0, 1.0)
        uv = flip_v(getattr(mesh.visual, "uv", None), n, f"{self.path.name}: material {entry.index}")
        return PartSurface(scaled_colours(np.tile(WHITE, (n, 1)), kd), uv, self._materials[entry.index], entry.index)

    def _material(self, entry: MtlMaterial) -> Material:
        base = normal = None
        normal_scale = 1.0
        if entry.map_kd is not None:
            px = self._image(entry.map_kd, "map_Kd")
            base = Image(image_key(self.sha256, entry.index, "base", px), px, True, f"{self.mtl_name}: {entry.map_kd}")
        if entry.bump is not None:
            px = self._image(entry.bump, "map_Bump")
            mean = px.reshape(-1, 3).mean(axis=0) / 255.0
            if mean[2] > NORMAL_MAP_BLUE and np.all(np.abs(mean[:2] - 0.5) <= NORMAL_MAP_RG):
                normal_scale = entry.bump_scale
            else:  # a height map: grey times -bm is the height in texel widths
                px = normal_map(px.astype(np.float64).mean(axis=2) / 255.0 * entry.bump_scale, 1.0)
            normal = Image(image_key(self.sha256, entry.index, "normal", px), px, False,
                           f"{self.mtl_name}: {entry.bump}")
        return Material(base=base, normal=normal, normal_scale=normal_scale, metallic_factor=0.0)

    def _image(self, ref: str, statement: str) -> np.ndarray:
        from PIL import Image as PILImage

        label = f"{self.mtl_where}: {statement} {ref!r}"
        path = resolve_beside(self.path, ref)
        if path is None:
            raise AssetError(f"{label}: no such file beside {self.path.name}")
        if path not in self._pixels:
            try:
                image = PILImage.open(path)
            except Exception as exc:  # not an image Pillow knows
                raise AssetError(f"{label}: cannot read as an image ({type(exc).__name__}: {exc})") from exc
            with image:
                self._pixels[path] = decode_image(image, label, self.budget)
        return self._pixels[path]


def surface_reader(path: Path, kind: str, where: str, name: str, sha256: str) -> GltfSurfaces | ObjSurfaces | None:
    """What reads the textured materials of the mesh file at `path` (format `kind`; errors call it `where`, the
    images' sources, which meta records, `name`: no folder, so meta does not depend on where files lie); None if it
    has none (no material names a texture, or a format without textures), so it loads as an untextured mesh."""
    if kind in ("gltf", "glb"):
        data = path.read_bytes()
        try:
            tree = gltf_tree(data, kind, where)
        except AssetError:  # not a glTF: loaded as untextured, trimesh's parser says what is wrong with it
            return None
        materials = tree.get("materials")
        if not isinstance(materials, list) or not all(isinstance(m, dict) for m in materials):
            return None
        if not any(texture_info(m, field, in_pbr) is not None for m in materials for _, field, in_pbr in TEXTURE_FIELDS):
            return None
        return GltfSurfaces(path, kind, where, name, sha256, data, tree)
    if kind == "obj":
        library, mtl = mtl_library(path, where)
        if mtl is None or not any(m.map_kd is not None or m.bump is not None for m in library.values()):
            return None
        return ObjSurfaces(path, where, name, sha256, library, mtl)
    return None
