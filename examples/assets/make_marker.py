"""Writes examples/assets/marker.glb: an underwater fiducial survey marker, a 0.3 m square orange plastic plate 2 cm
thick on four 3 cm legs, its top printed with a black and white 4x4-bit square code (ArUco-like, not from a real
dictionary; no rotation of it is itself, so a frame shows which way the marker lies) inside a white quiet zone and
an orange border. One glTF 2.0 material: a base colour texture, a normal map of slightly rough plastic (smooth
noise, about 3 degrees of slope), metallicFactor 0.

Deterministic: numpy's seeded generator and element-wise arithmetic only, and Pillow's PNG encoder (pinned in
constraints.txt), so running it again writes the same bytes (tests/test_user_textures.py checks this).

    python examples/assets/make_marker.py [OUT]   (default: marker.glb beside this script)
"""

from __future__ import annotations

import io
import json
import struct
import sys
from pathlib import Path

import numpy as np
from PIL import Image

SIDE_M, PLATE_M, LEG_M, LEG_SIDE_M, LEG_INSET_M = 0.30, 0.02, 0.03, 0.03, 0.02
TEXTURE_PX, BORDER_PX, CELLS = 256, 16, 8  # the code: quiet zone, black frame, 4x4 bits, black frame, quiet zone
NORMAL_PX, NORMAL_SLOPE = 128, 0.05  # normal map texels; rms slope of the plastic's roughness
ORANGE, WHITE, BLACK = (235, 110, 20), (245, 245, 240), (18, 18, 18)
BITS = np.array([[1, 0, 1, 1], [0, 1, 0, 0], [1, 1, 1, 0], [0, 0, 1, 0]], np.uint8)
SIDE_UV = (4 / TEXTURE_PX, 0.45, 12 / TEXTURE_PX, 0.55)  # a patch of the orange border for every other face


def base_colour() -> np.ndarray:
    """(256, 256, 3) uint8: the orange border, then 8x8 cells of 28 px: white quiet zone, black frame, the bits."""
    cells = np.zeros((CELLS, CELLS), np.uint8)  # 1 white, 0 black
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 1
    cells[2:6, 2:6] = BITS
    cell_px = (TEXTURE_PX - 2 * BORDER_PX) // CELLS
    code = np.where(np.kron(cells, np.ones((cell_px, cell_px), np.uint8))[..., None] == 1, WHITE, BLACK)
    image = np.tile(np.array(ORANGE, np.uint8), (TEXTURE_PX, TEXTURE_PX, 1))
    image[BORDER_PX:TEXTURE_PX - BORDER_PX, BORDER_PX:TEXTURE_PX - BORDER_PX] = code
    return image


def normal_texture() -> np.ndarray:
    """(128, 128, 3) uint8 tangent-space normals (glTF: x right, y towards the image's top) of smooth periodic
    noise: Gaussian noise blurred by six 3x3 box passes, scaled to NORMAL_SLOPE rms slope."""
    h = np.random.default_rng(20250601).standard_normal((NORMAL_PX, NORMAL_PX))
    for _ in range(6):
        h = sum(np.roll(np.roll(h, dy, 0), dx, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9.0
    hx = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / 2.0
    hy = (np.roll(h, 1, 0) - np.roll(h, -1, 0)) / 2.0  # towards the image's top
    scale = NORMAL_SLOPE / np.sqrt(np.mean(hx * hx + hy * hy))
    hx, hy = hx * scale, hy * scale
    z = 1.0 / np.sqrt(hx * hx + hy * hy + 1.0)
    n = np.stack([-hx * z, -hy * z, z], axis=-1)
    return np.clip(np.floor((n + 1.0) * 127.5 + 0.5), 0, 255).astype(np.uint8)


def box(lo, hi, top_uv: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An axis-aligned box (glTF frame: +y up) as 6 quads of their own vertices: positions, normals, uv, faces. The
    top quad maps the whole texture (its top edge towards -z, its right towards +x) when top_uv, else SIDE_UV."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pos, nrm, uv, faces = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_ax, v_ax = [(1, 2), (2, 0), (0, 1)][axis]  # u, v axes with u x v = +axis
            corners = []
            for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.where(sign > 0, hi, lo).astype(float)
                p[u_ax] = (lo, hi)[du][u_ax]
                p[v_ax] = (lo, hi)[dv][v_ax]
                corners.append(p)
            order = [0, 1, 2, 3] if sign > 0 else [0, 3, 2, 1]  # counter-clockwise seen from outside
            quad = [corners[k] for k in order]
            normal = np.zeros(3)
            normal[axis] = sign
            for p in quad:
                if top_uv and axis == 1 and sign > 0:
                    uv.append([(p[0] - lo[0]) / (hi[0] - lo[0]), (p[2] - lo[2]) / (hi[2] - lo[2])])
                else:
                    u0, v0, u1, v1 = SIDE_UV
                    k = len(uv) % 4
                    uv.append([(u0, u1)[k in (1, 2)], (v0, v1)[k in (2, 3)]])
                pos.append(p)
                nrm.append(normal)
            base = len(pos) - 4
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.array(pos), np.array(nrm), np.array(uv), np.array(faces)


def geometry() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The plate and its legs: positions (n, 3) float32 metres (glTF: +y up, the feet at y = 0), normals (n, 3)
    float32, uv (n, 2) float32 ((0, 0) the image's top-left), faces (m, 3) uint32."""
    s = SIDE_M / 2
    parts = [box([-s, LEG_M, -s], [s, LEG_M + PLATE_M, s], True)]
    a, b = s - LEG_INSET_M - LEG_SIDE_M, s - LEG_INSET_M
    for x0, x1 in ((-b, -a), (a, b)):
        for z0, z1 in ((-b, -a), (a, b)):
            parts.append(box([x0, 0.0, z0], [x1, LEG_M, z1], False))
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    pos = np.concatenate([p[0] for p in parts]).astype(np.float32)
    nrm = np.concatenate([p[1] for p in parts]).astype(np.float32)
    uv = np.concatenate([p[2] for p in parts]).astype(np.float32)
    faces = np.concatenate([p[3] + o for p, o in zip(parts, offsets)]).astype(np.uint32)
    return pos, nrm, uv, faces


def png(pixels: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def glb() -> bytes:
    """The marker as binary glTF 2.0 bytes."""
    pos, nrm, uv, faces = geometry()
    blob, views, accessors = bytearray(), [], []

    def view(data: bytes) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob.extend(data)
        return len(views) - 1

    def accessor(a: np.ndarray, kind: str, bounds: bool = False) -> int:
        acc = {"bufferView": view(a.tobytes()), "componentType": 5126 if a.dtype == np.float32 else 5125,
               "count": len(a), "type": kind}
        if bounds:
            acc.update(min=a.min(axis=0).tolist(), max=a.max(axis=0).tolist())
        accessors.append(acc)
        return len(accessors) - 1

    attributes = {"POSITION": accessor(pos, "VEC3", bounds=True), "NORMAL": accessor(nrm, "VEC3"),
                  "TEXCOORD_0": accessor(uv, "VEC2")}
    indices = accessor(faces.reshape(-1), "SCALAR")
    images = [{"bufferView": view(png(base_colour())), "mimeType": "image/png", "name": "code"},
              {"bufferView": view(png(normal_texture())), "mimeType": "image/png", "name": "plastic-normal"}]
    blob.extend(b"\0" * (-len(blob) % 4))
    tree = {
        "asset": {"version": "2.0", "generator": "seasynth examples/assets/make_marker.py"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "marker"}],
        "meshes": [{"name": "marker", "primitives": [{"attributes": attributes, "indices": indices, "material": 0}]}],
        "materials": [{"name": "printed-plastic",
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0,
                                                "roughnessFactor": 0.7},
                       "normalTexture": {"index": 1, "scale": 1.0}}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "textures": [{"source": 0, "sampler": 0}, {"source": 1, "sampler": 0}],
        "images": images, "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(blob)}],
    }
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + bytes(blob)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def main(argv: list[str]) -> None:
    code = np.array(BITS)
    assert all(not np.array_equal(code, np.rot90(code, k)) for k in (1, 2, 3)), "the code must show its rotation"
    out = Path(argv[1]) if len(argv) > 1 else Path(__file__).with_name("marker.glb")
    out.write_bytes(glb())


if __name__ == "__main__":
    main(sys.argv)
