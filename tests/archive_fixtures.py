"""Zip archives of textured meshes for the archive tests: good ones (a glTF with a PNG texture, an OBJ with its MTL
and PNG), made small with trimesh and Pillow, and the raw pieces to spoil them with."""

from __future__ import annotations

import io
import json
import stat
import struct
import warnings
import zipfile
import zlib

GLTF_ZIP = "boat.zip"  # what the tests upload the glTF archives as
SKIN = "boat/skin.png"  # the glTF's texture, named by URI


def png(width: int = 4, height: int = 4, colour: tuple[int, int, int] = (200, 30, 30)) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (width, height), colour).save(buf, format="PNG")
    return buf.getvalue()


def png_header_only(width: int, height: int) -> bytes:
    """A PNG that declares width x height pixels in a few dozen bytes."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0")) + chunk(b"IEND", b"")


def textured_box(image: bytes | None = None):
    """A unit box with UVs and a texture (4x4 red unless `image`)."""
    import numpy as np
    import trimesh
    from PIL import Image

    box = trimesh.creation.box()
    uv = np.random.default_rng(0).random((len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.open(io.BytesIO(image or png())))
    return box


def gltf_files(folder: str = "boat/", texture: bytes | None = None) -> dict[str, bytes]:
    """A textured box as glTF: model.gltf, its .bin buffers, and its texture as a PNG file named by URI (SKIN)."""
    import trimesh

    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(textured_box()))
    tree = json.loads(files.pop("model.gltf"))
    tree["images"] = [{"uri": "skin.png", "name": "skin"}]  # from a file, not the buffer trimesh wrote it into
    out = {f"{folder}{name}": data for name, data in files.items()}
    out[f"{folder}model.gltf"] = json.dumps(tree).encode()
    out[f"{folder}skin.png"] = texture if texture is not None else png()
    return out


def obj_files(folder: str = "") -> dict[str, bytes]:
    """A textured box as OBJ: model.obj, material.mtl and material_0.png."""
    import trimesh

    text, extras = trimesh.exchange.obj.export_obj(textured_box(png(4, 4, (20, 40, 220))), include_texture=True,
                                                   return_texture=True)
    return {f"{folder}model.obj": text.encode(), **{f"{folder}{k}": v for k, v in extras.items()}}


def zip_bytes(entries, compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    """A zip of (name or ZipInfo, bytes) entries, in order; a dict is its items. Duplicate names are kept. Named
    entries get a fixed date, so the same entries make the same bytes (the same asset id)."""
    entries = entries.items() if isinstance(entries, dict) else entries
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "Duplicate name": wanted here
        with zipfile.ZipFile(buf, "w", compression) as zf:
            for name, data in entries:
                if isinstance(name, str):
                    name = zipfile.ZipInfo(name, date_time=(2024, 1, 1, 0, 0, 0))
                    name.compress_type, name.external_attr = compression, 0o644 << 16
                zf.writestr(name, data)
    return buf.getvalue()


def glb(image: bytes | None = None, embed: str = "view") -> bytes:
    """A textured box as binary glTF; with `image`, that image replaces its texture, in the BIN chunk (embed="view"),
    as a base64 data URI (embed="data"), or (embed="file") not at all: the glTF names the file tex.png instead."""
    import base64

    import trimesh

    data = trimesh.Scene(textured_box()).export(file_type="glb")
    if image is None:
        return data
    json_size = struct.unpack_from("<I", data, 12)[0]
    tree = json.loads(data[20:20 + json_size])
    blob = bytearray(data[20 + json_size + 8:])
    if embed == "view":
        blob += b"\0" * (-len(blob) % 4)
        tree["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(image)})
        blob += image + b"\0" * (-len(image) % 4)
        tree["buffers"][0]["byteLength"] = len(blob)
        tree["images"] = [{"bufferView": len(tree["bufferViews"]) - 1, "mimeType": "image/png"}]
    elif embed == "data":
        tree["images"] = [{"uri": "data:image/png;base64," + base64.b64encode(image).decode()}]
    else:
        tree["images"] = [{"uri": "tex.png"}]
    text = json.dumps(tree).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + bytes(blob)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def special(name: str, mode: int) -> zipfile.ZipInfo:
    """A member whose Unix file type is `mode` (stat.S_IFLNK: a symbolic link; S_IFIFO: a named pipe)."""
    info = zipfile.ZipInfo(name)
    info.external_attr = (mode | 0o777) << 16
    return info


def symlink(name: str) -> zipfile.ZipInfo:
    return special(name, stat.S_IFLNK)


def encrypted(data: bytes, name: str) -> bytes:
    """`data` (a zip) with member `name` flagged encrypted (general purpose bit 0) in both of its headers."""
    out = bytearray(data)
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        local = zf.getinfo(name).header_offset
    out[local + 6] |= 1
    at = out.find(b"PK\x01\x02")
    while at >= 0:
        size = struct.unpack_from("<H", out, at + 28)[0]
        if out[at + 46:at + 46 + size] == name.encode():
            out[at + 8] |= 1
        at = out.find(b"PK\x01\x02", at + 4)
    return bytes(out)


def zeros(size: int) -> bytes:
    return b"\0" * size
