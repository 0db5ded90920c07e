"""seasynth.service.archives and seasynth.service.textures: member names accepted iff they stay inside the folder
they extract into, an extraction that is whole or absent (and idempotent, and safe to race), the limits, and the
references a mesh inside may follow; seasynth.worker.scene.assets.archive's cache keyed by the archive's sha256."""

from __future__ import annotations

import hashlib
import os
import threading
import zipfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service import archives
from seasynth.service.archives import ArchiveLimits, archive_members, member_parts, safe_extract
from seasynth.service.errors import AssetError
from seasynth.service.textures import check_glb
from tests.archive_fixtures import glb, gltf_files, obj_files, png, png_header_only, zeros, zip_bytes

# --- member names

SEGMENT = st.one_of(st.sampled_from(["..", ".", "", "a", "b.png", "model.gltf", "...", "..a", "a..", ". ."]),
                    st.text(st.characters(blacklist_characters="/\\:\0", blacklist_categories=("Cs",)), min_size=1,
                             max_size=12))
ROOTS = st.sampled_from(["", "/", "\\", "//", "\\\\", "C:", "c:\\", "Z:/", "/../"])


@settings(max_examples=1000)
@given(root=ROOTS, segments=st.lists(SEGMENT, min_size=1, max_size=6), seps=st.lists(st.sampled_from("/\\"),
                                                                                       min_size=6, max_size=6))
def test_a_name_is_accepted_iff_it_is_relative_and_has_no_dotdot_and_then_it_stays_inside(root, segments, seps):
    name = root + "".join(s + sep for s, sep in zip(segments[:-1], seps, strict=False)) + segments[-1]
    rooted = root != "" or (segments[0] == "" and len(segments) > 1)  # an empty first segment: a leading separator
    safe = not rooted and ".." not in segments and any(s not in ("", ".") for s in segments)
    try:
        parts = member_parts(name)
    except ValueError:
        assert not safe, name
        return
    assert safe, name
    assert parts == tuple(s for s in segments if s not in ("", "."))
    base = Path("/srv/extract")
    target = Path(os.path.normpath(base.joinpath(*parts)))
    assert target != base and target.is_relative_to(base)


@pytest.mark.parametrize(("name", "why"), [("../a.png", "'..'"), ("a/../../b", "'..'"), ("a\\..\\b", "'..'"),
                                           ("/etc/passwd", "absolute"), ("\\x\\y", "absolute"),
                                           ("C:/x", "drive letter"), ("c:x", "drive letter"), ("./", "names no file"),
                                           ("", "empty"), ("a/" + "x" * 256, "longer than 255 bytes")])
def test_unsafe_names_say_why(name, why):
    with pytest.raises(ValueError, match=why):
        member_parts(name)


# --- extraction: whole or absent, idempotent, raced


def write(tmp_path: Path, files, name: str = "boat.zip", **kw) -> Path:
    path = tmp_path / name
    path.write_bytes(zip_bytes(files, **kw))
    return path


def tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_safe_extract_writes_every_member_and_returns_the_mesh(tmp_path):
    files = {**gltf_files(), "boat/readme/notes.txt": b"hello"}
    dest = tmp_path / "out" / "boat"
    mesh = safe_extract(write(tmp_path, files), dest)
    assert mesh == dest / "boat" / "model.gltf"
    assert tree(dest) == files
    assert sorted(os.listdir(dest.parent)) == ["boat"]  # no temporary folder left beside it


def test_safe_extract_is_idempotent_and_writes_nothing_the_second_time(tmp_path, monkeypatch):
    zip_path, dest = write(tmp_path, obj_files()), tmp_path / "x"
    first = safe_extract(zip_path, dest)
    stamps = {p: p.stat().st_mtime_ns for p in dest.rglob("*")}

    def no_writing(*args):
        raise AssertionError("extracted again")

    monkeypatch.setattr(archives, "_write", no_writing)
    assert safe_extract(zip_path, dest) == first == dest / "model.obj"
    assert {p: p.stat().st_mtime_ns for p in dest.rglob("*")} == stamps


def test_a_failed_extraction_leaves_no_folder_at_all(tmp_path):
    """The member over the pixel budget is found after every file is written: still, dest never appears."""
    zip_path = write(tmp_path, gltf_files(texture=png_header_only(9000, 8000)))
    with pytest.raises(AssetError, match="boat.zip: member 'boat/skin.png': 9000x8000 pixels"):
        safe_extract(zip_path, tmp_path / "out" / "boat")
    assert os.listdir(tmp_path / "out") == []


def test_an_extraction_killed_half_way_is_never_used(tmp_path, monkeypatch):
    """A process killed mid-write leaves at most its temporary folder (here its cleanup is skipped, as a SIGKILL
    skips it), never `dest`; the next call extracts afresh beside the leftover."""
    zip_path, dest = write(tmp_path, obj_files()), tmp_path / "cache" / "k"
    real = archives._write

    def killed(zip_path, root, members, label):
        (root / "model.obj").write_bytes(b"v 0 0 0\n")  # half of what it would write
        raise KeyboardInterrupt

    monkeypatch.setattr(archives, "_write", killed)
    monkeypatch.setattr(archives.shutil, "rmtree", lambda path: None)
    with pytest.raises(KeyboardInterrupt):
        safe_extract(zip_path, dest)
    (leftover,) = os.listdir(dest.parent)
    assert leftover.startswith(".k.part-") and not dest.exists()
    monkeypatch.setattr(archives, "_write", real)
    assert safe_extract(zip_path, dest) == dest / "model.obj"
    assert tree(dest) == obj_files()


def test_a_foreign_or_incomplete_dest_is_refused_not_used(tmp_path):
    zip_path, dest = write(tmp_path, obj_files()), tmp_path / "d"
    dest.mkdir()
    (dest / "model.obj").write_bytes(b"something else")
    with pytest.raises(AssetError, match="is not this archive's extraction"):
        safe_extract(zip_path, dest)
    empty = tmp_path / "empty"
    empty.mkdir()  # an empty folder is no extraction yet: it is filled
    assert safe_extract(zip_path, empty) == empty / "model.obj"


def test_processes_racing_to_extract_one_archive_all_get_the_same_whole_folder(tmp_path):
    zip_path, dest = write(tmp_path, gltf_files()), tmp_path / "shared" / "sha"
    go, got, errors = threading.Barrier(8), [], []

    def run():
        go.wait()
        try:
            got.append(safe_extract(zip_path, dest))
        except Exception as err:  # noqa: BLE001 (collected, asserted empty below)
            errors.append(err)

    threads = [threading.Thread(target=run) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == [] and got == [dest / "boat" / "model.gltf"] * 8
    assert tree(dest) == gltf_files() and os.listdir(dest.parent) == ["sha"]


# --- limits and references


def test_limits_count_members_bytes_and_ratio(tmp_path):
    files = {**obj_files(), "pad.bin": zeros(4096)}
    zip_path = write(tmp_path, files)
    assert [m.name for m in archive_members(zip_path)] == list(files)
    with pytest.raises(AssetError, match=r"boat.zip: 4 members is over the limit of 3 \(member 'pad.bin'"):
        archive_members(zip_path, limits=ArchiveLimits(members=3))
    total = sum(len(v) for v in files.values())
    with pytest.raises(AssetError, match=f"member 'pad.bin': the members up to this one inflate to {total} bytes"):
        archive_members(zip_path, limits=ArchiveLimits(total_bytes=total - 1))
    with pytest.raises(AssetError, match="member 'pad.bin': inflates .* to 4096, more than 10 times"):
        archive_members(zip_path, limits=ArchiveLimits(ratio=10, ratio_floor_bytes=1000))
    stored = write(tmp_path, files, "stored.zip", compression=zipfile.ZIP_STORED)  # 1:1 whatever the limits
    assert len(archive_members(stored, limits=ArchiveLimits(ratio=1.01, ratio_floor_bytes=0))) == 4


@pytest.mark.parametrize(("mtl_ref", "why"), [("/etc/hosts", "names '/etc/hosts', which is an absolute path"),
                                              ("../up.png", "names '../up.png', which has a '..' component"),
                                              ("gone.png", "names 'gone.png', which the archive does not hold")])
def test_an_obj_may_name_only_files_of_its_archive(tmp_path, mtl_ref, why):
    files = obj_files("m/")
    files["m/material.mtl"] = files["m/material.mtl"].replace(b"material_0.png", mtl_ref.encode())
    with pytest.raises(AssetError) as err:
        safe_extract(write(tmp_path, files), tmp_path / "out")
    assert str(err.value).startswith(f"boat.zip: member 'm/material.mtl': {why}"), err.value
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("statement", ["map_Bump -bm 0.5 gone.png", "bump gone.png", "map_Kd -s 1 1 1 gone.png"])
def test_an_obj_s_bump_and_optioned_maps_are_checked_as_the_loader_reads_them(tmp_path, statement):
    """The check reads the MTL as the mesh loader does (seasynth.service.mtl: options before the file name), so an
    archive a worker would refuse at its first frame is refused here."""
    files = obj_files("m/")
    files["m/material.mtl"] += f"\n{statement}\n".encode()
    with pytest.raises(AssetError) as err:
        safe_extract(write(tmp_path, files), tmp_path / "out")
    assert str(err.value).startswith("boat.zip: member 'm/material.mtl': names 'gone.png', which the archive does "
                                     "not hold"), err.value


def test_a_glb_alone_embeds_its_images_and_may_name_no_file(tmp_path):
    path = tmp_path / "t.glb"
    path.write_bytes(glb(png(2, 2), "data"))
    check_glb(path, "t.glb")  # embedded: fine
    path.write_bytes(glb(png(2, 2), "file"))
    with pytest.raises(AssetError, match="t.glb: image 0: names the file 'tex.png'; a .glb upload embeds"):
        check_glb(path, "t.glb")


def test_a_glb_in_an_archive_may_name_files_beside_it(tmp_path):
    files = {"m/t.glb": glb(png(2, 2), "file"), "m/tex.png": png(3, 3)}
    assert safe_extract(write(tmp_path, files), tmp_path / "out") == tmp_path / "out" / "m" / "t.glb"
    files["m/tex.png"] = png_header_only(9000, 9000)
    with pytest.raises(AssetError, match="boat.zip: member 'm/tex.png': 9000x9000 pixels is over the limit"):
        safe_extract(write(tmp_path, files), tmp_path / "out2")


def test_a_jpeg_texture_counts_and_the_budget_is_per_asset(tmp_path):
    from io import BytesIO

    from PIL import Image

    buf = BytesIO()
    Image.new("RGB", (3, 2)).save(buf, format="JPEG")
    files = {**gltf_files(), "boat/extra.jpg": buf.getvalue(), "boat/big.png": png_header_only(8192, 8192)}
    from seasynth.service import textures

    seen = []
    real = textures.PixelBudget.add

    def spy(self, where, size):
        seen.append((where, size))
        real(self, where, size)

    textures.PixelBudget.add = spy
    try:
        safe_extract(write(tmp_path, files), tmp_path / "out")
    finally:
        textures.PixelBudget.add = real
    assert seen == [("boat.zip: member 'boat/skin.png'", (4, 4)), ("boat.zip: member 'boat/extra.jpg'", (3, 2)),
                    ("boat.zip: member 'boat/big.png'", (8192, 8192))]


def test_a_gltf_nesting_too_deeply_is_refused_naming_it(tmp_path):
    files = {"m/model.gltf": b"[" * 100_000 + b"]" * 100_000}
    with pytest.raises(AssetError, match="boat.zip: member 'm/model.gltf': not a valid gltf mesh .its JSON nests too deeply"):
        safe_extract(write(tmp_path, files), tmp_path / "out")


# --- the worker's cache


def test_mesh_in_archive_extracts_once_under_the_archives_sha256_and_trimesh_reads_the_texture(tmp_path, monkeypatch):
    import tempfile

    import trimesh

    from seasynth.worker.scene.assets.archive import CACHE_FOLDER, mesh_in_archive

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    zip_path = write(tmp_path, gltf_files())
    sha = hashlib.sha256(zip_path.read_bytes()).hexdigest()
    mesh = mesh_in_archive(zip_path)
    assert mesh == tmp_path / "tmp" / CACHE_FOLDER / sha / "boat" / "model.gltf"
    assert mesh_in_archive(zip_path) == mesh
    (geometry,) = trimesh.load_scene(str(mesh)).geometry.values()
    assert geometry.visual.material.baseColorTexture.size == (4, 4)
    bad = write(tmp_path, {**gltf_files(), "../x": b""}, "bad.zip")
    with pytest.raises(AssetError, match="bad.zip: member '../x': the name has a '..' component"):
        mesh_in_archive(bad)


def test_every_newmtl_gets_its_own_index_even_a_name_given_twice():
    from seasynth.service.mtl import read_mtl

    found = read_mtl("newmtl A\nmap_Kd a1.png\nnewmtl A\nmap_Kd a2.png\nnewmtl B\nmap_Kd b.png\n", "t.mtl")
    assert {k: (m.index, m.map_kd) for k, m in found.items()} == {"A": (1, "a2.png"), "B": (2, "b.png")}
