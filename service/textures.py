"""Texture budgets of uploaded meshes: every image a glTF, GLB or OBJ references or embeds must be a PNG or JPEG
within a decoded-pixel budget, read from its header without decoding its pixels."""

from __future__ import annotations

import base64
import binascii
import io
import json
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from seasynth.service.errors import AssetError
from seasynth.service.mtl import read_mtl
from seasynth.service.settings import MAX_ASSET_PIXELS, MAX_IMAGE_PIXELS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
# Names Pillow (and so trimesh) may decode as an image: in an archive each must be a PNG or JPEG within budget.
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tga", ".tif", ".tiff", ".webp"})
GLB_HEADER = struct.Struct("<4sII")  # magic, version, length
GLB_CHUNK = struct.Struct("<I4s")  # length, type

# (reference as written in a mesh file, how messages name the referring file) -> (the file it names, how messages
# name that file); AssetError for a reference that may not be followed or names nothing.
Resolve = Callable[[str, str], tuple[Path, str]]


@dataclass
class PixelBudget:
    """The decoded pixels of one asset's textures, counted as they are checked."""

    asset: str  # how messages name the asset
    per_image: int = MAX_IMAGE_PIXELS
    total: int = MAX_ASSET_PIXELS
    used: int = 0

    def add(self, where: str, size: tuple[int, int]) -> None:
        """Count an image of `size` (w, h) that messages call `where`; AssetError past either limit."""
        w, h = size
        if w * h > self.per_image:
            raise AssetError(f"{where}: {w}x{h} pixels is over the limit of {self.per_image} pixels for a texture")
        self.used += w * h
        if self.used > self.total:
            raise AssetError(f"{where}: {w}x{h} pixels brings the textures of {self.asset} to {self.used} pixels, "
                             f"over the limit of {self.total} for one asset")


def image_size(fp: BinaryIO, where: str) -> tuple[int, int]:
    """(width, height) of the PNG or JPEG in the seekable `fp`, from its header (no pixel is decoded); AssetError
    naming `where` for anything else or a header Pillow cannot read."""
    from PIL import JpegImagePlugin, PngImagePlugin

    head = fp.read(8)
    fp.seek(0)
    if head.startswith(PNG_MAGIC):
        cls, fmt = PngImagePlugin.PngImageFile, "PNG"
    elif head.startswith(JPEG_MAGIC):
        cls, fmt = JpegImagePlugin.JpegImageFile, "JPEG"
    else:
        raise AssetError(f"{where}: not a PNG or JPEG image")
    try:
        # The plugin class itself, not Image.open: it reads the header and stops, and Image.open's own bomb check
        # would refuse large images without saying their size.
        image = cls(fp)
    except Exception as err:  # any header Pillow cannot parse (truncated, a chunk inflating too far, ...)
        raise AssetError(f"{where}: cannot read as a {fmt} image ({type(err).__name__}: {err})") from err
    w, h = image.size
    if w == 0 or h == 0:
        raise AssetError(f"{where}: the image is empty")
    return w, h


def check_image_file(path: Path, where: str, budget: PixelBudget) -> None:
    with open(path, "rb") as f:
        budget.add(where, image_size(f, where))


def check_textures(mesh: Path, fmt: str, where: str, resolve: Resolve, budget: PixelBudget) -> set[Path]:
    """Check every image the mesh file at `mesh`, of format `fmt` (gltf, glb or obj; any other has none; messages
    call it `where`) references or embeds, counting each into `budget`; return the image files it checked. Files are
    found through `resolve`, exactly those trimesh would read: a glTF's buffer and image URIs, an OBJ's first
    `mtllib` and the `map_Kd` images of that library."""
    if fmt == "obj":
        return _obj_textures(mesh, where, resolve, budget)
    if fmt not in ("gltf", "glb"):
        return set()
    with open(mesh, "rb") as f:
        tree, bin_chunk = _glb_parts(f, where) if fmt == "glb" else (_json(f.read(), where, fmt), None)
        try:
            return _gltf_textures(tree, f, bin_chunk, where, resolve, budget)
        except AssetError:
            raise
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as err:  # a tree of the wrong shape
            raise AssetError(f"{where}: not a valid {fmt} mesh ({type(err).__name__}: {err})") from err


def check_glb(path: Path, name: str) -> None:
    """A single .glb upload: its embedded images within budget; a URI naming another file is refused (there is
    none beside it)."""

    def nothing_beside(ref: str, referrer: str) -> tuple[Path, str]:
        raise AssetError(f"{referrer}: names the file {ref!r}; a .glb upload embeds its buffers and images (upload "
                         "a .zip holding the files a glTF names)")

    check_textures(path, "glb", name, nothing_beside, PixelBudget(name))


def _json(data: bytes, where: str, fmt: str) -> dict[str, Any]:
    try:
        tree = json.loads(data)
    except ValueError as err:
        raise AssetError(f"{where}: not a valid {fmt} mesh (its JSON does not parse: {err})") from err
    except RecursionError:
        raise AssetError(f"{where}: not a valid {fmt} mesh (its JSON nests too deeply)") from None
    if not isinstance(tree, dict):
        raise AssetError(f"{where}: not a valid {fmt} mesh (its JSON is not an object)")
    return tree


def _glb_parts(f: BinaryIO, where: str) -> tuple[dict[str, Any], tuple[int, int] | None]:
    """The JSON tree of a binary glTF and its BIN chunk as (offset, length) in the file (not read here)."""
    head = f.read(GLB_HEADER.size)
    if len(head) < GLB_HEADER.size or head[:4] != b"glTF":
        raise AssetError(f"{where}: not a valid glb mesh (no glTF binary header)")
    _, version, length = GLB_HEADER.unpack(head)
    if version != 2:
        raise AssetError(f"{where}: not a valid glb mesh (version {version}; glTF 2.0 is read)")
    tree, bin_chunk, offset = None, None, GLB_HEADER.size
    while offset + GLB_CHUNK.size <= length:
        f.seek(offset)
        chunk = f.read(GLB_CHUNK.size)
        if len(chunk) < GLB_CHUNK.size:
            break
        size, kind = GLB_CHUNK.unpack(chunk)
        if kind == b"JSON" and tree is None:
            tree = _json(f.read(size), where, "glb")
        elif kind == b"BIN\0" and bin_chunk is None:
            bin_chunk = (offset + GLB_CHUNK.size, size)
        offset += GLB_CHUNK.size + size
    if tree is None:
        raise AssetError(f"{where}: not a valid glb mesh (no JSON chunk)")
    return tree, bin_chunk


def _embedded(uri: str) -> bytes | None:
    """The bytes of a base64 data URI, None for a reference to a file (as trimesh tells them apart)."""
    index = uri.find("base64,")
    if index < 0:
        return None
    try:
        return base64.b64decode(uri[index + 7:])
    except (binascii.Error, ValueError) as err:
        raise ValueError(f"bad base64 data ({err})") from err


def _gltf_textures(tree: dict[str, Any], f: BinaryIO, bin_chunk: tuple[int, int] | None, where: str,
                   resolve: Resolve, budget: PixelBudget) -> set[Path]:
    buffers: list[Callable[[int, int], bytes]] = []  # (offset, length) -> bytes of buffer i
    for i, buffer in enumerate(tree.get("buffers", [])):
        uri = buffer.get("uri")
        if uri is None:  # the GLB's own BIN chunk
            if bin_chunk is None:
                raise ValueError(f"buffer {i} has no uri and there is no BIN chunk")
            buffers.append(_file_slice(f, *bin_chunk))
        elif (data := _embedded(uri)) is not None:
            buffers.append(lambda offset, length, data=data: data[offset:offset + length])
        else:  # trimesh reads every buffer: each must be a file the resolver may give
            path, _ = resolve(uri, f"{where}: buffer {i}")
            buffers.append(_path_slice(path))
    views = tree.get("bufferViews", [])
    checked: set[Path] = set()
    for i, image in enumerate(tree.get("images", [])):
        label = f"{where}: image {i}" + (f" ({image['name']!r})" if isinstance(image.get("name"), str) else "")
        if "uri" in image:
            data = _embedded(image["uri"])
            if data is None:
                path, member = resolve(image["uri"], label)
                if path not in checked:
                    check_image_file(path, member, budget)
                    checked.add(path)
                continue
        else:
            view = views[image["bufferView"]]
            data = buffers[view["buffer"]](int(view.get("byteOffset", 0)), int(view["byteLength"]))
        budget.add(label, image_size(io.BytesIO(data), label))
    return checked


def _file_slice(f: BinaryIO, start: int, size: int) -> Callable[[int, int], bytes]:
    def read(offset: int, length: int) -> bytes:
        offset, length = max(0, offset), max(0, min(length, size - offset))
        f.seek(start + offset)
        return f.read(length)

    return read


def _path_slice(path: Path) -> Callable[[int, int], bytes]:
    def read(offset: int, length: int) -> bytes:
        with open(path, "rb") as g:
            g.seek(max(0, offset))
            return g.read(max(0, length))

    return read


def _obj_textures(mesh: Path, where: str, resolve: Resolve, budget: PixelBudget) -> set[Path]:
    """The OBJ's material library (its first `mtllib`, the rest of that line, as trimesh reads it) and the
    `map_Kd` and bump images its materials name, read as the mesh loader reads them (seasynth.service.mtl)."""
    ref = _after(mesh, b"mtllib")
    if not ref:
        return set()
    mtl, mtl_member = resolve(ref, where)
    checked: set[Path] = set()
    with open(mtl, "rb") as f:
        materials = read_mtl(f.read().decode("utf-8", "replace"), mtl_member)
    for material in materials.values():
        for image in (material.map_kd, material.bump):
            if not image:
                continue
            path, member = resolve(image, mtl_member)
            if path not in checked:
                check_image_file(path, member, budget)
                checked.add(path)
    return checked


def _after(path: Path, key: bytes) -> str:
    """The rest of the first line holding `key` (anywhere in it, as trimesh finds it), stripped; '' if none."""
    with open(path, "rb") as f:
        for raw in f:
            if (index := raw.find(key)) >= 0:
                return raw[index + len(key):].decode("utf-8", "replace").strip()
    return ""
