"""User meshes keep their textures per pixel (worker.scene.assets.surfaces): a glTF quad's checker lands texel for
texel, the right way round, in the clean and hazed image through the session's render path; several materials
stay apart; OBJ/MTL maps load the right way round (map_Bump as a height or a normal map); a zipped glTF renders
the bytes of the unzipped one; images over the pixel budget and images that do not decode are refused naming the
file; baseColorFactor multiplies the vertex colours in linear light; meta records the materials."""

from __future__ import annotations

import base64
import hashlib
import io
import json
import struct
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from PIL import Image as PILImage
from test_textures_render import AMBIENT_ONLY, VIEW, WATER, H, W, pixel_uv, rotation

from seasynth.service.errors import AssetError
from seasynth.service.settings import MAX_IMAGE_PIXELS
from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.frame.formation import haze
from seasynth.worker.frame.function import to_render_mesh
from seasynth.worker.frame.srgb import decode_srgb8, encode_srgb8
from seasynth.worker.render import DrawItem, Passes, Sampling, View
from seasynth.worker.scene.assets.textures import normal_map
from seasynth.worker.scene.assets.user import load_user_asset, read_mesh

# The loaded quads' object frame: front towards -y, the image's right +x, its top +z, base at z = 0. This puts
# the image's right along the camera's x, its top along -y (up) and the front towards the camera.
OBJ_TO_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
CORNERS = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0]], np.uint8)  # TL, TR, BL, BR
CORNER_IMAGE = np.repeat(np.repeat(CORNERS.reshape(2, 2, 3), 2, 0), 2, 1)  # 2x2 texels a quarter: quarter centres
# fall between texels of one colour, so filtering mixes in nothing else


def png(pixels: np.ndarray) -> bytes:
    buf = io.BytesIO()
    PILImage.fromarray(np.asarray(pixels, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def quad_arrays(half: float, x0: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A glTF quad (+y up) in the xy plane facing +z: positions, glTF texture coordinates ((0, 0) the image's
    top-left, at (-half, +half)) and faces."""
    pos = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float32)
    pos[:, 0] += x0
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    return pos, uv, np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def write_gltf(path: Path, primitives: list[tuple], materials: list[dict], images: list, webp: bool = False) -> Path:
    """A glTF written by hand: `path`'s suffix picks .gltf (buffer in `<stem>.bin` beside it) or .glb (one BIN
    chunk). primitives: (positions, uv or None, faces, material index or None); images: bytes (embedded) or a URI;
    webp: textures name their images through EXT_texture_webp only."""
    blob = bytearray()
    views, accessors = [], []

    def view(data: bytes) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob.extend(data)
        return len(views) - 1

    def accessor(a: np.ndarray, kind: str) -> int:
        acc = {"bufferView": view(a.tobytes()), "componentType": 5126 if a.dtype == np.float32 else 5125,
               "count": int(a.size // {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[kind]), "type": kind}
        if kind == "VEC3":
            acc.update(min=a.min(axis=0).tolist(), max=a.max(axis=0).tolist())
        accessors.append(acc)
        return len(accessors) - 1

    prims = []
    for pos, uv, faces, material in primitives:
        attributes = {"POSITION": accessor(pos, "VEC3")}
        if uv is not None:
            attributes["TEXCOORD_0"] = accessor(uv, "VEC2")
        prim = {"attributes": attributes, "indices": accessor(faces.reshape(-1), "SCALAR")}
        if material is not None:
            prim["material"] = material
        prims.append(prim)
    mime = "image/webp" if webp else "image/png"
    image_specs = [{"bufferView": view(i), "mimeType": mime} if isinstance(i, bytes) else {"uri": i} for i in images]
    blob.extend(b"\0" * (-len(blob) % 4))
    tree = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": prims}], "materials": materials, "accessors": accessors, "bufferViews": views,
            "buffers": [{"byteLength": len(blob)}]}
    if images:
        textures = [{"extensions": {"EXT_texture_webp": {"source": k}}} if webp else {"source": k}
                    for k in range(len(images))]
        tree.update(images=image_specs, textures=textures)
    if webp:
        tree.update(extensionsUsed=["EXT_texture_webp"], extensionsRequired=["EXT_texture_webp"])
    if path.suffix == ".glb":
        text = json.dumps(tree).encode()
        text += b" " * (-len(text) % 4)
        body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + blob
        path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    else:
        tree["buffers"][0]["uri"] = f"{path.stem}.bin"
        (path.parent / f"{path.stem}.bin").write_bytes(bytes(blob))
        path.write_text(json.dumps(tree))
    return path


def textured(texture: int = 0, **extra) -> dict:
    """A glTF material with a base colour texture and no metal (glTF's default metallicFactor is 1)."""
    return {"pbrMetallicRoughness": {"baseColorTexture": {"index": texture}, "metallicFactor": 0.0, **extra}}


def placed(asset, centre, R: np.ndarray | None = None) -> DrawItem:
    """The asset drawn as the session draws a placed user asset (to_render_mesh with its surface), its quad's
    centre (object (0, 0, half)) at `centre` and its image turned by R in the camera frame."""
    M = np.eye(4)
    M[:3, :3] = (np.eye(3) if R is None else R) @ OBJ_TO_CAM
    half = float(asset.mesh.vertices[:, 2].max()) / 2.0
    M[:3, 3] = np.asarray(centre, float) - M[:3, :3] @ [0.0, 0.0, half]
    return DrawItem(mesh=to_render_mesh(asset.key, asset.mesh, surface=asset.surface), world_from_obj=M,
                    albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32), instance_id=1)


def checked_pixels(colours: np.ndarray, texels: int, centre, R, half: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mask, expected colour (h, w, 3) uint8, range m) of a checker of `colours` (checks, checks, 3), `texels`
    texels a check: the mask holds the pixels whose samples' filter footprints all fall inside one check, half a
    texel from its edges, with the texture magnified (test_textures_render's criterion)."""
    checks, n_tex = colours.shape[0], colours.shape[0] * texels
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    corners = np.stack([np.stack([xs + dx, ys + dy], -1) for dx in (-1.0, 1.0) for dy in (-1.0, 1.0)], -2)
    uv, _ = pixel_uv(corners, centre, R, half)
    _, range_m = pixel_uv(np.stack([xs, ys], -1), centre, R, half)
    cell = np.floor(uv * checks).astype(int)
    same = np.all(cell == cell[..., :1, :], axis=(-2, -1)) & np.all((cell >= 0) & (cell < checks), axis=(-2, -1))
    margin = 0.5 / n_tex
    inner = np.all((uv * checks - cell) / checks > margin, axis=(-2, -1)) & np.all(
        (cell + 1 - uv * checks) / checks > margin, axis=(-2, -1))
    footprint = np.abs(uv.max(axis=-2) - uv.min(axis=-2)).max(axis=-1) * n_tex
    c = np.clip(cell[..., 0, :], 0, checks - 1)
    return same & inner & (footprint < 2.0), colours[c[..., 1], c[..., 0]], range_m


def render(renderer, items, **passes):
    return renderer.render(VIEW, items, AMBIENT_ONLY, WATER, Sampling(msaa=4), Passes(**passes))


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(checks=st.integers(2, 5), texels=st.integers(2, 5), seed=st.integers(0, 2**32 - 1), binary=st.booleans(),
       yaw=st.floats(-0.5, 0.5), pitch=st.floats(-0.5, 0.5), roll=st.floats(-0.3, 0.3), distance=st.floats(1.2, 2.2))
def test_a_gltf_checker_lands_per_pixel_the_right_way_round(render_session, checks, texels, seed, binary, yaw,
                                                            pitch, roll, distance):
    assume(checks * texels <= 20)  # magnified: a texel spans more than a pixel
    colours = np.random.default_rng(seed).integers(0, 256, (checks, checks, 3)).astype(np.uint8)
    image = np.repeat(np.repeat(colours, texels, 0), texels, 1)
    half = 0.5
    with tempfile.TemporaryDirectory() as tmp:
        path = write_gltf(Path(tmp) / ("quad.glb" if binary else "quad.gltf"), [(*quad_arrays(half), 0)],
                          [textured()], [png(image)])
        asset = load_user_asset(path)
    assert asset.surface is not None and len(asset.surface.groups) == 1
    R, centre = rotation(yaw, pitch, roll), np.array([0.0, 0.0, distance])
    out = render(render_session.renderer, [placed(asset, centre, R)], clean=True)
    ok, texel, range_m = checked_pixels(colours, texels, centre, R, half)
    assert ok.sum() >= 40
    expected_J = decode_srgb8(texel, np.float64)
    np.testing.assert_allclose(out.clean[ok], expected_J[ok], atol=2e-3)
    np.testing.assert_allclose(out.image[ok], haze(expected_J, range_m, WATER.beta_D, WATER.beta_B, WATER.B_inf)[ok],
                               atol=2e-3)
    assert len(np.unique(texel[ok], axis=0)) >= 2


def corner_colours(clean: np.ndarray) -> np.ndarray:
    """The 8-bit colours at the centres of the four quarters of a quad 1 m across seen face on 2 m away."""
    f = VIEW.K[0, 0]
    d = round(f * 0.25 / 2.0)
    cx, cy = (W - 1) / 2, (H - 1) / 2
    at = [(cy - d, cx - d), (cy - d, cx + d), (cy + d, cx - d), (cy + d, cx + d)]  # TL, TR, BL, BR on screen
    return np.array([encode_srgb8(clean[round(y), round(x)]) for y, x in at])


def test_a_gltf_texture_is_upright_and_not_mirrored(render_session, tmp_path):
    path = write_gltf(tmp_path / "corners.gltf", [(*quad_arrays(0.5), 0)], [textured()], ["corners.png"])
    (tmp_path / "corners.png").write_bytes(png(CORNER_IMAGE))
    out = render(render_session.renderer, [placed(load_user_asset(path), [0.0, 0.0, 2.0])], clean=True)
    np.testing.assert_array_equal(corner_colours(out.clean), CORNERS)


def test_two_materials_keep_their_own_colours(render_session, tmp_path):
    """One primitive textured, one with a plain colour: the plain one keeps the vertex colours read_mesh bakes."""
    left, right = quad_arrays(0.25, x0=-0.3), quad_arrays(0.25, x0=0.3)
    plain = {"pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.6, 0.4, 1.0]}}
    path = write_gltf(tmp_path / "two.glb", [(*left, 0), (*right, 1)], [textured(), plain], [png(CORNER_IMAGE)])
    asset = load_user_asset(path)
    groups = asset.surface.groups
    assert [(count, m is None) for _, count, m in groups] == [(2, False), (2, True)]
    baked, _ = read_mesh(path)  # the plain quad's 4 vertices come second in both
    np.testing.assert_array_equal(asset.mesh.visual.vertex_colors[4:], baked.visual.vertex_colors[4:])
    plain_colour = asset.mesh.visual.vertex_colors[4, :3]
    out = render(render_session.renderer, [placed(asset, [0.0, 0.0, 2.0])], clean=True)
    f, cy = VIEW.K[0, 0], (H - 1) / 2
    right_px = encode_srgb8(out.clean[round(cy), round((W - 1) / 2 + f * 0.3 / 2.0)])
    np.testing.assert_array_equal(right_px, plain_colour)
    # the left quad's quarters, a quad 0.5 m across centred 0.3 m left
    d, x = f * 0.125 / 2.0, (W - 1) / 2 - f * 0.3 / 2.0
    got = [encode_srgb8(out.clean[round(cy + sy * d), round(x + sx * d)])
           for sy, sx in ((-1, -1), (-1, 1), (1, -1), (1, 1))]
    np.testing.assert_array_equal(got, CORNERS)


def write_obj(folder: Path, bump: str | None) -> Path:
    """An OBJ quad facing -y (z up, as OBJ files are read), vt (0, 0) at its bottom-left, with map_Kd and an
    optional bump statement."""
    (folder / "corners.png").write_bytes(png(CORNER_IMAGE))
    mtl = "newmtl skin\nKd 1 1 1\nmap_Kd corners.png\n" + (f"{bump}\n" if bump else "")
    (folder / "quad.mtl").write_text(mtl)
    obj = ("mtllib quad.mtl\nv -0.5 0 -0.5\nv 0.5 0 -0.5\nv 0.5 0 0.5\nv -0.5 0 0.5\n"
           "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl skin\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    (folder / "quad.obj").write_text(obj)
    return folder / "quad.obj"


def test_an_obj_with_map_kd_and_a_height_bump_loads_the_right_way_round(render_session, tmp_path):
    height = np.tile(np.linspace(0, 255, 8).astype(np.uint8)[None, :, None], (8, 1, 3))
    (tmp_path / "height.png").write_bytes(png(height))
    asset = load_user_asset(write_obj(tmp_path, "map_Bump -bm 0.5 height.png"))
    material = asset.surface.groups[0][2]
    np.testing.assert_array_equal(material.normal.pixels, normal_map(height[..., 0] / 255.0 * 0.5, 1.0))
    assert material.normal_scale == 1.0 and material.base.srgb and not material.normal.srgb
    # the ambient light does not turn with the normal: the colours are the texels'
    out = render(render_session.renderer, [placed(asset, [0.0, 0.0, 2.0])], clean=True)
    np.testing.assert_array_equal(corner_colours(out.clean), CORNERS)


def test_an_obj_bump_that_looks_like_a_normal_map_is_one(tmp_path):
    normals = np.tile(np.array([120, 136, 250], np.uint8), (4, 4, 1))
    (tmp_path / "n.png").write_bytes(png(normals))
    material = load_user_asset(write_obj(tmp_path, "bump -bm 0.7 n.png")).surface.groups[0][2]
    np.testing.assert_array_equal(material.normal.pixels, normals)
    assert material.normal_scale == 0.7


def test_a_zipped_gltf_renders_the_bytes_of_the_unzipped_one(render_session, tmp_path):
    folder = tmp_path / "boat"
    folder.mkdir()
    path = write_gltf(folder / "boat.gltf", [(*quad_arrays(0.5), 0)], [textured()], ["skin.png"])
    (folder / "skin.png").write_bytes(png(np.random.default_rng(3).integers(0, 256, (6, 6, 3))))
    archive = tmp_path / "boat.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for name in ("boat.gltf", "boat.bin", "skin.png"):
            z.write(folder / name, f"boat/{name}")
    zipped, plain = load_user_asset(archive), load_user_asset(path)
    assert zipped.sha256 == hashlib.sha256(archive.read_bytes()).hexdigest() != plain.sha256
    a = render(render_session.renderer, [placed(zipped, [0.0, 0.0, 2.0])], srgb8=True).image
    b = render(render_session.renderer, [placed(plain, [0.0, 0.0, 2.0])], srgb8=True).image
    assert a.tobytes() == b.tobytes() and len(np.unique(a.reshape(-1, 3), axis=0)) > 10


def test_an_image_over_the_pixel_budget_is_refused_naming_the_file_and_image(tmp_path):
    side = int(np.ceil(np.sqrt(MAX_IMAGE_PIXELS + 1)))
    big = PILImage.new("1", (side, side))
    big.save(tmp_path / "huge.png", optimize=False)
    path = write_gltf(tmp_path / "big.gltf", [(*quad_arrays(0.5), 0)], [textured()], ["huge.png"])
    with pytest.raises(AssetError, match=r"big\.gltf: image 0 \('huge\.png'\): .* over the limit"):
        load_user_asset(path)


@pytest.mark.parametrize("content", [b"not a png at all", png(CORNER_IMAGE)[:60]], ids=["garbage", "truncated"])
def test_a_texture_that_does_not_decode_is_refused_naming_the_file(tmp_path, content):
    (tmp_path / "skin.png").write_bytes(content)
    path = write_gltf(tmp_path / "bad.gltf", [(*quad_arrays(0.5), 0)], [textured()], ["skin.png"])
    with pytest.raises(AssetError, match=r"bad\.gltf: image 0 \('skin\.png'\)"):
        load_user_asset(path)


@settings(max_examples=20, deadline=None)
@given(factor=st.tuples(*[st.floats(0.0, 1.0)] * 3))
def test_base_colour_factor_multiplies_the_vertex_colours_in_linear_light(factor):
    with tempfile.TemporaryDirectory() as tmp:
        path = write_gltf(Path(tmp) / "f.glb", [(*quad_arrays(0.5), 0)], [textured(baseColorFactor=[*factor, 1.0])],
                          [png(CORNER_IMAGE)])
        asset = load_user_asset(path)
    want = encode_srgb8(np.array(factor, np.float64))
    np.testing.assert_array_equal(asset.mesh.visual.vertex_colors[:, :3], np.tile(want, (4, 1)))


def test_gltf_material_fields_are_read(tmp_path):
    """normalTexture's scale, occlusion (red) and metallic-roughness (green, blue) packed into one image at the
    larger size, occlusion strength and metallicFactor (1 where absent)."""
    occlusion = np.full((2, 2, 3), 100, np.uint8)
    metal_rough = np.zeros((4, 4, 3), np.uint8)
    metal_rough[..., 1], metal_rough[..., 2] = 50, 200
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 2}},
                "normalTexture": {"index": 1, "scale": 0.4}, "occlusionTexture": {"index": 3, "strength": 0.6}}
    images = [png(CORNER_IMAGE), png(np.full((2, 2, 3), [128, 128, 255])), png(metal_rough), png(occlusion)]
    m = load_user_asset(write_gltf(tmp_path / "pbr.glb", [(*quad_arrays(0.5), 0)], [material], images)
                        ).surface.groups[0][2]
    assert (m.normal_scale, m.occlusion_strength, m.metallic_factor) == (0.4, 0.6, 1.0)
    assert m.orm.pixels.shape == (4, 4, 3)
    np.testing.assert_array_equal(m.orm.pixels[..., 0], 100)
    np.testing.assert_array_equal(m.orm.pixels[..., 1:], metal_rough[..., 1:])
    assert m.base.key.startswith(f"file/{load_user_asset(tmp_path / 'pbr.glb').sha256}/0/base/")


def test_meta_records_a_user_assets_materials(render_session, tmp_path):
    path = write_gltf(tmp_path / "quad.glb", [(*quad_arrays(0.15), 0)], [textured()], [png(CORNER_IMAGE)])
    spec = parse_spec({"seed": 3, "frames": 1, "quality": "draft",
                       "camera": {"width": 64, "height": 48, "hfov_deg": 60.0},
                       "targets": {"class_name": "Tile", "count": [1, 1], "assets": [{"path": str(path)}]},
                       "distractors": {"count": [0, 0]}})
    files = render_session.frame_files(spec, 0)
    meta = json.loads(files["meta/000000.json"])
    (obj,) = [o for o in meta["objects"] if o["role"] == "target"]
    (group,) = obj["materials"]
    assert (group["first_face"], group["face_count"]) == (0, 2)
    assert group["material"]["images"]["base"]["key"].startswith(f"file/{obj['asset']['sha256']}/0/base/")
    assert "material" not in obj  # the procedural assets' field


def test_textures_without_a_source_keep_their_own_images(tmp_path):
    """EXT_texture_webp names its image in the extension (the texture has no `source`): two such textures stay two
    images."""
    images = [np.full((4, 4, 3), c, np.uint8) for c in ((200, 10, 10), (10, 10, 200))]

    def webp(pixels: np.ndarray) -> bytes:
        buf = io.BytesIO()
        PILImage.fromarray(pixels).save(buf, format="WEBP", lossless=True)
        return buf.getvalue()

    path = write_gltf(tmp_path / "w.glb", [(*quad_arrays(0.25, -0.3), 0), (*quad_arrays(0.25, 0.3), 1)],
                      [textured(0), textured(1)], [webp(i) for i in images], webp=True)
    groups = load_user_asset(path).surface.groups
    assert len(groups) == 2
    for (_, _, material), pixels in zip(groups, images):
        np.testing.assert_array_equal(material.base.pixels, pixels)


def test_base64_images_load(tmp_path):
    uri = "data:image/png;base64," + base64.b64encode(png(CORNER_IMAGE)).decode()
    m = load_user_asset(write_gltf(tmp_path / "b.gltf", [(*quad_arrays(0.5), 0)], [textured()], [uri])
                        ).surface.groups[0][2]
    np.testing.assert_array_equal(m.base.pixels, CORNER_IMAGE)


MARKER = Path(__file__).resolve().parents[1] / "examples" / "assets" / "marker.glb"


def test_make_marker_writes_the_committed_bytes(tmp_path):
    """examples/assets/make_marker.py is deterministic: with the pinned numpy and Pillow (constraints.txt) it
    writes examples/assets/marker.glb byte for byte."""
    out = tmp_path / "marker.glb"
    subprocess.run([sys.executable, str(MARKER.with_name("make_marker.py")), str(out)], check=True)
    assert out.read_bytes() == MARKER.read_bytes()
    assert len(out.read_bytes()) < 200_000


def test_the_marker_seen_from_above_shows_its_code_upright(render_session):
    """Looking straight down, with the file's -z (the code's top edge) up the image, each of the 8x8 cells of the
    code (quiet zone, frame and bits) has the colour the script printed there."""
    sys.path.insert(0, str(MARKER.parent))
    try:
        import make_marker
    finally:
        sys.path.remove(str(MARKER.parent))
    asset = load_user_asset(MARKER)
    w = h = 256
    f = 400.0
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    cam = np.eye(4)
    cam[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # x right, world +y up the image, looking down
    cam[:3, 3] = [0.0, 0.0, 0.5]
    view = View(K=K, width=w, height=h, cam_from_world=cam, near=0.05, far=10.0)
    item = DrawItem(mesh=to_render_mesh(asset.key, asset.mesh, surface=asset.surface), world_from_obj=np.eye(4),
                    albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32), instance_id=1)
    clean = render_session.renderer.render(view, [item], AMBIENT_ONLY, None, Sampling(), Passes(clean=True)).clean
    texture = make_marker.base_colour()
    side, border, cells = make_marker.SIDE_M, make_marker.BORDER_PX, make_marker.CELLS
    cell_px = (make_marker.TEXTURE_PX - 2 * border) // cells
    top = float(asset.mesh.vertices[:, 2].max())
    for i in range(cells):
        for j in range(cells):
            tx, ty = border + cell_px * (j + 0.5), border + cell_px * (i + 0.5)  # texel column, row
            x = -side / 2 + tx / make_marker.TEXTURE_PX * side
            y = side / 2 - ty / make_marker.TEXTURE_PX * side
            p = cam[:3, :3] @ [x, y, top] + cam[:3, 3]
            u, v = K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]
            got = encode_srgb8(clean[round(v), round(u)])
            np.testing.assert_array_equal(got, texture[int(ty), int(tx)], err_msg=f"cell {i}, {j}")
