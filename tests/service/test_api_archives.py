"""Zip uploads over real HTTP (real Redis, moto's S3): a zipped glTF and a zipped OBJ with their textures are stored
as .zip meshes; each kind of bad archive, and a GLB embedding an image over the pixel budget, is 422 naming the
archive and the member at fault, and stores nothing."""

from __future__ import annotations

import hashlib
import json
import stat
from collections.abc import Iterator

import httpx
import pytest
from hardening import KEY, VERSION, serving
from service_stack import Stack, tiny_spec

from seasynth.service.shards import asset_info_key, asset_key
from tests.archive_fixtures import (
    encrypted,
    glb,
    gltf_files,
    obj_files,
    png,
    png_header_only,
    special,
    symlink,
    zeros,
    zip_bytes,
)


@pytest.fixture(scope="module")
def roomy(infra: Stack) -> Iterator[tuple[httpx.Client, object]]:
    """An API taking uploads up to 1 MiB (an archive of 1,000 members is 100 KB), and its services."""
    from seasynth.api.deps import open_services
    from seasynth.api.main import create_app

    settings = infra.settings(key_prefix="archives", worker_version=VERSION, max_asset_bytes=2**20, api_keys=KEY)
    services = open_services(settings)
    try:
        with serving(create_app(settings, services)) as url, \
                httpx.Client(base_url=url, headers={"X-API-Key": KEY}, timeout=120) as client:
            yield client, services
    finally:
        services.close()


def gltf_with(**image) -> dict[str, bytes]:
    """The good glTF archive with its image entry replaced."""
    files = gltf_files()
    tree = json.loads(files["boat/model.gltf"])
    tree["images"] = [{"name": "skin", **image}]
    return {**files, "boat/model.gltf": json.dumps(tree).encode()}


def crc_broken() -> bytes:
    """The good glTF archive, stored, with the last byte of its texture flipped (its CRC-32 no longer matches)."""
    texture = png(5, 5)
    data = bytearray(zip_bytes(gltf_files(texture=texture), compression=0))
    at = data.find(texture) + len(texture) - 1
    data[at] ^= 0xFF
    return bytes(data)


GOOD = gltf_files()
MANY = [*GOOD.items(), *((f"boat/notes/{i}.txt", b"") for i in range(1000))]
BIG = [(f"boat/t{i}.png", png_header_only(8000, 8000)) for i in range(5)]
M = "boat.zip: member "
# id, archive bytes, what the one error line starts with, and what else it says
BAD = [
    ("dotdot", zip_bytes({**GOOD, "boat/../../evil.png": png()}),
     f"{M}'boat/../../evil.png': the name has a '..' component", "relative names"),
    ("absolute", zip_bytes({**GOOD, "/etc/cron.d/evil": b"x"}), f"{M}'/etc/cron.d/evil': the name is an absolute",
     ""),
    ("backslash-rooted", zip_bytes({**GOOD, "\\evil.txt": b"x"}), f"{M}'\\\\evil.txt': the name is an absolute", ""),
    ("drive", zip_bytes({**GOOD, "C:/evil.txt": b"x"}), f"{M}'C:/evil.txt': the name starts with a drive letter", ""),
    ("symlink", zip_bytes([*GOOD.items(), (symlink("boat/link.png"), b"/etc/passwd")]),
     f"{M}'boat/link.png': the member is a symbolic link", ""),
    ("fifo", zip_bytes([*GOOD.items(), (special("boat/pipe", stat.S_IFIFO), b"")]),
     f"{M}'boat/pipe': the member is not a regular file", ""),
    ("duplicate", zip_bytes([*GOOD.items(), ("boat/skin.png", png(2, 2))]),
     f"{M}'boat/skin.png': a second member named 'boat/skin.png'", ""),
    ("file-as-folder", zip_bytes({**GOOD, "boat/skin.png/x.txt": b""}),
     f"{M}'boat/skin.png/x.txt': lies in 'boat/skin.png', which member 'boat/skin.png' is a file", ""),
    ("too-many", zip_bytes(MANY), "boat.zip: 1006 members is over the limit of 1000",
     f"(member '{MANY[1000][0]}' is the first past it)"),
    ("encrypted", encrypted(zip_bytes(GOOD), "boat/skin.png"), f"{M}'boat/skin.png': the member is encrypted", ""),
    ("image-over-budget", zip_bytes(gltf_files(texture=png_header_only(9000, 8000))),
     f"{M}'boat/skin.png': 9000x8000 pixels is over the limit of 67108864 pixels for a texture", ""),
    ("asset-over-budget", zip_bytes({**GOOD, **dict(BIG)}),
     f"{M}'boat/t4.png': 8000x8000 pixels brings the textures of boat.zip to 320000016 pixels", "268435456"),
    ("not-png-or-jpeg", zip_bytes({**GOOD, "boat/extra.bmp": b"BM" + bytes(60)}),
     f"{M}'boat/extra.bmp': not a PNG or JPEG image", ""),
    ("reference-outside", zip_bytes(gltf_with(uri="../../etc/passwd")),
     f"{M}'boat/model.gltf': image 0 ('skin'): names '../../etc/passwd', which has a '..' component", ""),
    ("reference-missing", zip_bytes(gltf_with(uri="gone.png")),
     f"{M}'boat/model.gltf': image 0 ('skin'): names 'gone.png', which the archive does not hold", ""),
    ("no-mesh", zip_bytes({"boat/skin.png": png()}), "boat.zip: no member is a mesh", ".gltf, .glb, .obj"),
    ("two-meshes", zip_bytes({**GOOD, **obj_files("boat/")}),
     "boat.zip: members 'boat/model.gltf' and 'boat/model.obj' are both meshes", ""),
    ("too-deep", zip_bytes(obj_files("a/b/")), f"{M}'a/b/model.obj': the mesh lies more than one folder deep", ""),
    ("bad-mesh", zip_bytes({"boat/model.gltf": b"{not json", "boat/skin.png": png()}),
     f"{M}'boat/model.gltf': not a valid gltf mesh (its JSON does not parse", ""),
    ("no-triangles", zip_bytes({"model.obj": b"v 0 0 0\n"}), f"{M}'model.obj': the obj mesh has no triangles", ""),
    ("corrupt", b"PK\x03\x04 this is no zip", "boat.zip: not a readable zip archive (", ""),
    ("truncated", zip_bytes(GOOD)[:-30], "boat.zip: not a readable zip archive (", ""),
    ("crc", crc_broken(), f"{M}'boat/skin.png': cannot be inflated (Bad CRC-32", ""),
    ("bomb", zip_bytes({**GOOD, "boat/pad.bin": zeros(16 * 2**20)}),
     f"{M}'boat/pad.bin': inflates ", "bytes to 16777216, more than 100 times (a zip bomb?)"),
]


@pytest.mark.parametrize(("data", "error", "also"), [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_archives_are_422_naming_the_member_and_store_nothing(roomy, data, error, also):
    client, services = roomy
    assert len(data) < 2**20
    r = client.post("/assets", files={"file": ("boat.zip", data)})
    assert r.status_code == 422, r.text
    (line,) = r.json()["errors"]
    assert line.startswith(error) and also in line, line
    asset_id = hashlib.sha256(data).hexdigest()
    assert services.store.head(asset_key(asset_id)) is None
    assert services.store.head(asset_info_key(asset_id)) is None


@pytest.mark.parametrize("kind", ["gltf", "obj"])
def test_zipped_textured_meshes_are_stored_as_zip_meshes(roomy, kind):
    client, services = roomy
    data = zip_bytes(gltf_files() if kind == "gltf" else obj_files())
    asset_id = hashlib.sha256(data).hexdigest()
    r = client.post("/assets", files={"file": (f"{kind}-boat.ZIP", data)})
    assert r.status_code == 201, r.text
    assert r.json() == {"asset_id": asset_id, "filename": f"{kind}-boat.ZIP", "bytes": len(data), "format": "zip",
                        "kind": "mesh"}
    assert services.store.get_bytes(asset_key(asset_id)) == data
    # Workers name their copy by the sidecar's suffix: .zip tells them to extract it.
    assert json.loads(services.store.get_bytes(asset_info_key(asset_id)))["filename"].lower().endswith(".zip")
    again = client.post("/assets", files={"file": ("again.zip", data)})
    assert (again.status_code, again.json()["asset_id"]) == (200, asset_id), again.text


def test_a_zip_asset_is_a_mesh_for_datasets_and_not_a_texture(roomy):
    client, _ = roomy
    asset_id = client.post("/assets", files={"file": ("ship.zip", zip_bytes(gltf_files("ship/")))}).json()["asset_id"]
    wrong = tiny_spec(terrain={"cells": 16, "variants": 1, "texture": {"asset_id": asset_id}})
    r = client.post("/datasets", json=wrong)
    assert r.status_code == 422, r.text
    need = f"terrain.texture.asset_id: asset {asset_id} is a mesh (zip); this field needs an image"
    assert r.json()["errors"] == [need]
    r = client.post("/datasets", json=tiny_spec(targets={"count": [1, 1], "assets": [{"asset_id": asset_id}]}))
    assert r.status_code == 202, r.text
    assert client.post(f"/datasets/{r.json()['id']}/cancel").json()["state"] == "cancelled"


GLBS = [
    ("view", glb(png_header_only(9000, 8000)), "big.glb: image 0: 9000x8000 pixels is over the limit of 67108864"),
    ("data", glb(png_header_only(9000, 8000), "data"), "big.glb: image 0: 9000x8000 pixels is over the limit"),
    ("not-an-image", glb(b"GIF89a" + bytes(20)), "big.glb: image 0: not a PNG or JPEG image"),
]


@pytest.mark.parametrize(("data", "error"), [g[1:] for g in GLBS], ids=[g[0] for g in GLBS])
def test_a_glbs_embedded_images_are_held_to_the_pixel_budget(roomy, data, error):
    client, services = roomy
    r = client.post("/assets", files={"file": ("big.glb", data)})
    assert r.status_code == 422, r.text
    (line,) = r.json()["errors"]
    assert line.startswith(error), line
    assert services.store.head(asset_key(hashlib.sha256(data).hexdigest())) is None


def test_a_textured_glb_is_stored(roomy):
    client, _ = roomy
    r = client.post("/assets", files={"file": ("boat.glb", glb(png(6, 6)))})
    assert r.status_code == 201, r.text
    assert (r.json()["format"], r.json()["kind"]) == ("glb", "mesh")
