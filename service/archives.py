"""Zip uploads of textured meshes (a glTF with its buffers and images, an OBJ with its MTL and images): the checks
of their members, shared by the API's upload check and the workers, and one safe, atomic extraction.

An archive is accepted when every member is a regular file or a folder, unencrypted, stored or deflated (bzip2 and
LZMA too), under a relative name without `..`; no name repeats; there are at most ARCHIVE_MAX_MEMBERS members
inflating to at most ARCHIVE_MAX_BYTES together, none more than ARCHIVE_MAX_RATIO times its compressed size (above
ARCHIVE_RATIO_FLOOR_BYTES); exactly one member is a mesh (.gltf, .glb or .obj), at the top level or in a folder
there; the files the mesh names lie beside it or below its folder; and every image (each file the mesh names as a
texture, each image a glTF embeds, each member named like an image) is a PNG or JPEG within the pixel budgets
(seasynth.service.textures).
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import tempfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

from seasynth.service.errors import AssetError
from seasynth.service.settings import (
    ARCHIVE_MAX_BYTES,
    ARCHIVE_MAX_MEMBERS,
    ARCHIVE_MAX_RATIO,
    ARCHIVE_RATIO_FLOOR_BYTES,
)
from seasynth.service.textures import IMAGE_SUFFIXES, PixelBudget, check_image_file, check_textures

MESH_SUFFIXES = (".gltf", ".glb", ".obj")
COMPRESSIONS = {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA}
DRIVE = re.compile(r"^[A-Za-z]:")
MAX_NAME_BYTES = 255  # one component, as most file systems allow
CHUNK = 1 << 20


@dataclass(frozen=True)
class ArchiveLimits:
    members: int = ARCHIVE_MAX_MEMBERS
    total_bytes: int = ARCHIVE_MAX_BYTES
    ratio: float = ARCHIVE_MAX_RATIO
    ratio_floor_bytes: int = ARCHIVE_RATIO_FLOOR_BYTES


LIMITS = ArchiveLimits()


@dataclass(frozen=True)
class Member:
    """One checked member: `name` as the archive spells it, `path` where it extracts (relative, normalised)."""

    name: str
    path: PurePosixPath
    size: int  # bytes, inflated
    compressed: int  # bytes, in the archive
    is_dir: bool


def member_parts(name: str) -> tuple[str, ...]:
    """The components of a member name or a mesh's file reference, `/` and `\\` both separators, `.` and empty ones
    dropped; ValueError saying why for a name that could land outside the folder it is extracted into (a `..`
    component; a name rooted at `/` or `\\`, or starting with a drive letter) or that no file can have."""
    if not name:
        raise ValueError("is empty")
    if "\0" in name:
        raise ValueError("holds a NUL character")
    if name[0] in "/\\":
        raise ValueError("is an absolute path")
    if DRIVE.match(name):
        raise ValueError("starts with a drive letter")
    parts = tuple(p for p in re.split(r"[/\\]", name) if p not in ("", "."))
    if ".." in parts:
        raise ValueError("has a '..' component")
    if not parts:
        raise ValueError("names no file")
    if any(len(p.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES for p in parts):
        raise ValueError(f"has a component longer than {MAX_NAME_BYTES} bytes")
    return parts


def archive_members(zip_path: Path, *, name: str | None = None, limits: ArchiveLimits = LIMITS) -> list[Member]:
    """Every member of the zip at `zip_path`, checked from its central directory alone (nothing is inflated);
    AssetError naming the archive (`name`, default its file name) and the member at fault."""
    label = name or Path(zip_path).name
    try:
        with zipfile.ZipFile(zip_path) as zf:
            infos = zf.infolist()
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError) as err:
        raise AssetError(f"{label}: not a readable zip archive ({err})") from None
    except OSError as err:
        raise AssetError(f"{label}: cannot read the archive ({err.strerror or err})") from err
    if len(infos) > limits.members:
        raise AssetError(f"{label}: {len(infos)} members is over the limit of {limits.members} (member "
                         f"{infos[limits.members].filename!r} is the first past it)")
    members: list[Member] = []
    seen: dict[PurePosixPath, str] = {}
    total = 0
    for info in infos:
        where = f"{label}: member {info.filename!r}"
        try:
            parts = member_parts(info.filename)
        except ValueError as why:
            raise AssetError(f"{where}: the name {why}; members must have relative names inside the archive") from None
        path = PurePosixPath(*parts)
        if path in seen:
            raise AssetError(f"{where}: a second member named {str(path)!r} (the first is {seen[path]!r})")
        seen[path] = info.filename
        is_dir = _kind(info, where)
        if info.flag_bits & 0x1:
            raise AssetError(f"{where}: the member is encrypted; upload an archive without a password")
        if info.compress_type not in COMPRESSIONS:
            raise AssetError(f"{where}: compression method {info.compress_type} is not one of stored, deflate, "
                             "bzip2 or LZMA")
        total += info.file_size
        if total > limits.total_bytes:
            raise AssetError(f"{where}: the members up to this one inflate to {total} bytes, over the limit of "
                             f"{limits.total_bytes} bytes for an archive")
        if info.file_size > limits.ratio_floor_bytes and info.file_size > limits.ratio * max(info.compress_size, 1):
            raise AssetError(f"{where}: inflates {info.compress_size} bytes to {info.file_size}, more than "
                             f"{limits.ratio:g} times (a zip bomb?)")
        members.append(Member(info.filename, path, info.file_size, info.compress_size, is_dir))
    files = {m.path: m for m in members if not m.is_dir}
    for m in members:
        for parent in m.path.parents:
            if parent in files:
                raise AssetError(f"{label}: member {m.name!r}: lies in {str(parent)!r}, which member "
                                 f"{files[parent].name!r} is a file")
    return members


def _kind(info: zipfile.ZipInfo, where: str) -> bool:
    """Whether a member is a folder; AssetError for a symbolic link or any other member that is not a regular file
    (the Unix file type in the high 16 bits of external_attr; none there, as DOS tools and Python's writestr
    leave it, is a regular file, or a folder if the name ends in a separator)."""
    kind = stat.S_IFMT(info.external_attr >> 16)
    if kind == stat.S_IFLNK:
        raise AssetError(f"{where}: the member is a symbolic link; archives may hold only files and folders")
    if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
        raise AssetError(f"{where}: the member is not a regular file (file type {oct(kind)}); archives may hold only "
                         "files and folders")
    return kind == stat.S_IFDIR or info.filename.endswith(("/", "\\"))


def mesh_member(members: list[Member], label: str) -> Member:
    """The one mesh of an archive (.gltf, .glb or .obj, at the top level or in a folder there)."""
    meshes = [m for m in members if not m.is_dir and m.path.suffix.lower() in MESH_SUFFIXES]
    if not meshes:
        raise AssetError(f"{label}: no member is a mesh; an archive holds one {', '.join(MESH_SUFFIXES)} file with "
                         "the files it names")
    if len(meshes) > 1:
        raise AssetError(f"{label}: members {meshes[0].name!r} and {meshes[1].name!r} are both meshes; an archive "
                         "holds exactly one")
    (mesh,) = meshes
    if len(mesh.path.parts) > 2:
        raise AssetError(f"{label}: member {mesh.name!r}: the mesh lies more than one folder deep; put it at the "
                         "archive's top level or in a folder there")
    return mesh


def safe_extract(zip_path: Path, dest: Path, *, name: str | None = None, limits: ArchiveLimits = LIMITS) -> Path:
    """Extract the checked archive at `zip_path` into the folder `dest`; return the path of its one mesh there.

    The members are checked (archive_members, mesh_member), written into a fresh temporary folder beside `dest`,
    their textures checked, and only then is that folder renamed to `dest` in one step: a `dest` that exists is
    complete. If `dest` already holds this archive's extraction (every file at its size), nothing is written, so a
    second call, or a process that lost the race to rename, returns the same path. AssetError names the archive
    (`name`, default its file name) and the member at fault; nothing is left behind then.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    label = name or zip_path.name
    members = archive_members(zip_path, name=label, limits=limits)
    mesh = mesh_member(members, label)
    if dest.exists() and not (dest.is_dir() and not any(dest.iterdir())):  # an empty folder is renamed over
        return _complete(dest, members, mesh, label)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}.part-"))
    try:
        _write(zip_path, tmp, members, label)
        _check_images(tmp, members, mesh, label)
        try:
            os.rename(tmp, dest)
        except OSError:  # another process renamed its complete extraction first
            return _complete(dest, members, mesh, label)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return dest / mesh.path


def _complete(dest: Path, members: list[Member], mesh: Member, label: str) -> Path:
    for m in members:
        target = dest / m.path
        if not (target.is_dir() if m.is_dir else target.is_file() and target.stat().st_size == m.size):
            raise AssetError(f"{label}: {dest} exists but is not this archive's extraction (member {m.name!r} "
                             "is not there as extracted)")
    return dest / mesh.path


def _write(zip_path: Path, root: Path, members: list[Member], label: str) -> None:
    """Every member under `root`: folders made, files written new ('xb') and never past their stated size."""
    with zipfile.ZipFile(zip_path) as zf:
        for info, m in zip(zf.infolist(), members, strict=True):
            target = root.joinpath(*m.path.parts)
            if m.is_dir:
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            written = 0
            try:
                with zf.open(info) as src, open(target, "xb") as out:
                    while chunk := src.read(CHUNK):
                        written += len(chunk)
                        if written > m.size:
                            raise AssetError(f"{label}: member {m.name!r}: inflates past its stated {m.size} bytes")
                        out.write(chunk)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as err:
                raise AssetError(f"{label}: member {m.name!r}: cannot be inflated ({err})") from None
            except OSError as err:
                raise AssetError(f"{label}: member {m.name!r}: cannot be extracted ({err.strerror or err})") from err


def _check_images(root: Path, members: list[Member], mesh: Member, label: str) -> None:
    """The textures the mesh names or embeds, then every other member named like an image, in one budget."""
    files = {m.path for m in members if not m.is_dir}
    folder = mesh.path.parent

    def resolve(ref: str, referrer: str) -> tuple[Path, str]:
        try:
            parts = member_parts(ref)
        except ValueError as why:
            raise AssetError(f"{referrer}: names {ref!r}, which {why}; a mesh in an archive names files beside it "
                             "or below its folder") from None
        wanted = folder.joinpath(*parts)
        # As written, URL-decoded (a glTF URI), or by its last component beside the mesh (trimesh's fallback).
        for candidate in (wanted, PurePosixPath(unquote(str(wanted))), folder / parts[-1]):
            if candidate in files:
                return root.joinpath(*candidate.parts), f"{label}: member {str(candidate)!r}"
        raise AssetError(f"{referrer}: names {ref!r}, which the archive does not hold (looked for "
                         f"{str(wanted)!r})")

    budget = PixelBudget(label)
    checked = check_textures(root.joinpath(*mesh.path.parts), mesh.path.suffix[1:].lower(),
                             f"{label}: member {mesh.name!r}", resolve, budget)
    for m in members:
        path = root.joinpath(*m.path.parts)
        if not m.is_dir and m.path.suffix.lower() in IMAGE_SUFFIXES and path not in checked:
            check_image_file(path, f"{label}: member {m.name!r}", budget)
