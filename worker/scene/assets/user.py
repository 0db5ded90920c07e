"""User-supplied files: meshes (glTF/GLB, OBJ, PLY, STL, or one of the first three zipped) as assets or seabed terrains, and terrain textures."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import numpy as np
import trimesh

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.render import Material
from seasynth.worker.scene.assets import Asset, AssetError, UserSurface, file_identity, freeze, read_source
from seasynth.worker.scene.assets.archive import mesh_in_archive
from seasynth.worker.scene.assets.surfaces import surface_reader
from seasynth.worker.scene.assets.terrain import Terrain, Texture, decode_texture

FORMATS = {".glb": "glb", ".gltf": "gltf", ".obj": "obj", ".ply": "ply", ".stl": "stl", ".zip": "zip"}  # zip: one of
# the first three with its files (seasynth.worker.scene.assets.archive)
Y_UP_FORMATS = frozenset({"glb", "gltf"})  # glTF is +y up by specification; everything else is kept as is
MID_GREY = np.array([128, 128, 128, 255], dtype=np.uint8)


def load_user_asset(path: Path) -> Asset:
    """A user mesh as an `Asset` (units as in the file, +z up, base at z = 0, x, y centred).

    Cached per process by (resolved path, mtime, size). `AssetError` names the file and the reason.
    """
    resolved, mtime_ns, size = file_identity(path)
    return _user_asset(resolved, mtime_ns, size)


def load_user_terrain(path: Path) -> Terrain:
    """A user mesh as a `Terrain` (x, y centred, lowest point at z = 0); cached like `load_user_asset`.

    `height_at` interpolates a height grid rasterised once at load (about `len(faces) / 2` samples,
    32-512 a side) from the highest surface over each sample; ray casting would need rtree or
    embree, which the worker does not ship. Grid points over no surface take the nearest height.
    """
    resolved, mtime_ns, size = file_identity(path)
    return _user_terrain(resolved, mtime_ns, size)


def load_user_texture(path: Path) -> Texture:
    """An image file decoded as a terrain `Texture`; cached like `load_user_asset`, so each process reads it once.

    `AssetError` names the file if it is missing, unreadable or not an image.
    """
    resolved, mtime_ns, size = file_identity(path)
    return _user_texture(resolved, mtime_ns, size)


@functools.lru_cache(maxsize=128)
def _user_asset(path: Path, mtime_ns: int, size: int) -> Asset:
    mesh, sha256, surface = read_user_mesh(path, textured=True)
    return Asset(key=f"file/{sha256}", mesh=freeze(mesh), sha256=sha256, source=path.name, surface=surface)


@functools.lru_cache(maxsize=8)
def _user_terrain(path: Path, mtime_ns: int, size: int) -> Terrain:
    mesh, sha256 = read_mesh(path)
    vertices = np.asarray(mesh.vertices)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    if not (hi[0] > lo[0] and hi[1] > lo[1]):
        raise AssetError(f"{path}: terrain mesh has no extent in x or y")
    extent = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    side = int(np.clip(np.sqrt(len(mesh.faces) / 2.0), 32, 512))
    scale = side / max(hi[0] - lo[0], hi[1] - lo[1])
    shape = (max(2, round((hi[1] - lo[1]) * scale) + 1), max(2, round((hi[0] - lo[0]) * scale) + 1))
    lookup = top_surface(vertices, np.asarray(mesh.faces), extent, shape)
    lookup.flags.writeable = False
    return Terrain(key=f"terrain/file/{sha256}", mesh=freeze(mesh), heights=None, extent=extent, lookup=lookup,
                   sha256=sha256)


@functools.lru_cache(maxsize=8)
def _user_texture(path: Path, mtime_ns: int, size: int) -> Texture:
    return decode_texture(read_source(path), str(path))


def read_mesh(path: Path) -> tuple[trimesh.Trimesh, str]:
    """Parse, flatten, colour and normalise a mesh file -> (mesh, sha256 hex of the file's bytes).

    Scenes are flattened with their transforms; textures and materials are baked to vertex colours
    (colours are taken as trimesh reports them, i.e. as sRGB); uncoloured geometry is mid grey.
    A `.zip` is read as the one mesh inside it (seasynth.worker.scene.assets.archive); sha256 is the zip's.
    """
    mesh, sha256, _ = read_user_mesh(path, textured=False)
    return mesh, sha256


def read_user_mesh(path: Path, textured: bool) -> tuple[trimesh.Trimesh, str, UserSurface | None]:
    """`read_mesh`, and with `textured` the file's textures kept per pixel (seasynth.worker.scene.assets.surfaces):
    parts whose material names a texture are coloured by its factor instead of baking it, and come back in a
    `UserSurface` (None if no part has one: the mesh is then `read_mesh`'s), their faces reordered so that each
    material's are one range."""
    data = read_source(path)
    sha256 = hashlib.sha256(data).hexdigest()
    kind = FORMATS.get(path.suffix.lower())
    if kind is None:
        raise AssetError(f"{path}: unsupported mesh format {path.suffix!r}; supported: {', '.join(FORMATS)}")
    mesh_path, where, name = path, str(path), path.name
    if kind == "zip":
        mesh_path = mesh_in_archive(path)
        kind, where, name = FORMATS[mesh_path.suffix.lower()], f"{path}: {mesh_path.name}", f"{name}: {mesh_path.name}"
    try:
        reader = surface_reader(mesh_path, kind, where, name, sha256) if textured else None
        if reader is None:  # by path, so OBJ materials and textures resolve
            scene = trimesh.load_scene(str(mesh_path), file_type=kind)
            parts = [(g, np.asarray(g.vertices, dtype=np.float64), np.asarray(g.faces, dtype=np.int64))
                     for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
            surfaces = [None] * len(parts)
        else:
            parts = placed_parts(reader.load_scene())
            surfaces = [reader.part(g) for g, _, _ in parts]
        colours = [vertex_colours(g) if s is None else s.colours for (g, _, _), s in zip(parts, surfaces)]
    except AssetError:
        raise
    except Exception as exc:  # any parser failure is a bad file: re-raised, naming it
        raise AssetError(f"{where}: cannot parse as {kind} ({type(exc).__name__}: {exc})") from exc
    if not parts:
        raise AssetError(f"{where}: contains no triangles")
    textured_parts = any(s is not None for s in surfaces)
    if textured_parts:  # each material's parts together, in the order the materials first appear
        first = {}
        for k, s in enumerate(surfaces):
            first.setdefault(-1 if s is None else s.group, k)
        order = sorted(range(len(parts)), key=lambda k: first[-1 if surfaces[k] is None else surfaces[k].group])
        parts, surfaces, colours = [parts[k] for k in order], [surfaces[k] for k in order], [colours[k] for k in order]
    vertices = [v for _, v, _ in parts]
    offsets = np.cumsum([0] + [len(v) for v in vertices[:-1]])
    faces = np.concatenate([f + o for (_, _, f), o in zip(parts, offsets)])
    v = np.concatenate(vertices)
    if not np.all(np.isfinite(v)):
        raise AssetError(f"{where}: vertices contain NaN or infinity")
    if kind in Y_UP_FORMATS:
        v = np.column_stack([v[:, 0], -v[:, 2], v[:, 1]])  # +y up -> +z up (rotation about x)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]]
    mesh = trimesh.Trimesh(vertices=v, faces=faces, vertex_colors=np.concatenate(colours), process=False)
    if not textured_parts:
        return mesh, sha256, None
    uv = np.concatenate([np.zeros((len(g), 2)) if s is None else s.uv for (_, g, _), s in zip(parts, surfaces)])
    uv = uv.astype(np.float32)
    uv.flags.writeable = False
    return mesh, sha256, UserSurface(uv=uv, groups=face_groups([len(f) for _, _, f in parts], surfaces))


def placed_parts(scene: trimesh.Scene) -> list[tuple[trimesh.Trimesh, np.ndarray, np.ndarray]]:
    """(mesh, vertices (n, 3) float64, faces (m, 3) int64) of every triangle mesh of a scene as placed by its
    graph, as `Scene.dump` places them but without copying the meshes (which would decode their textures)."""
    parts = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        g = scene.geometry[name]
        if not isinstance(g, trimesh.Trimesh) or not len(g.faces):
            continue
        T = np.asarray(transform, dtype=np.float64)
        faces = np.asarray(g.faces, dtype=np.int64)
        if np.linalg.det(T[:3, :3]) < 0:  # a mirroring transform: keep the faces' winding, as dump does
            faces = faces[:, ::-1]
        parts.append((g, np.asarray(g.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3], faces))
    return parts


def face_groups(face_counts: list[int], surfaces: list) -> tuple[tuple[int, int, Material | None], ...]:
    """(first face, face count, material) ranges of consecutive parts with one material (None: untextured)."""
    groups: list[list] = []
    start = 0
    for count, s in zip(face_counts, surfaces):
        material = None if s is None else s.material
        if groups and groups[-1][2] is material:
            groups[-1][1] += count
        else:
            groups.append([start, count, material])
        start += count
    return tuple((int(a), int(b), m) for a, b, m in groups)


def vertex_colours(mesh: trimesh.Trimesh) -> np.ndarray:
    """Per-vertex RGBA (n, 4) uint8 of any trimesh visual: textures sampled, none -> mid grey."""
    visual = mesh.visual
    if visual.kind == "texture":
        visual = visual.to_color()
    if visual.kind is None:
        return np.tile(MID_GREY, (len(mesh.vertices), 1))
    colours = np.asarray(visual.vertex_colors, dtype=np.uint8)
    if colours.shape != (len(mesh.vertices), 4):  # e.g. a single material colour
        colours = np.broadcast_to(colours.reshape(-1, 4)[0], (len(mesh.vertices), 4))
    return np.array(colours)


def top_surface(vertices: np.ndarray, faces: np.ndarray, extent: tuple[float, float, float, float],
                shape: tuple[int, int]) -> np.ndarray:
    """Highest surface z (ny, nx) float64 metres on a regular grid spanning `extent`.

    Rasterises every non-vertical triangle over the grid points inside it (vectorised over all
    triangle-sample pairs); points over no triangle take the value of the nearest covered point.
    """
    from scipy import ndimage

    ny, nx = shape
    xmin, xmax, ymin, ymax = extent
    dx, dy = (xmax - xmin) / (nx - 1), (ymax - ymin) / (ny - 1)
    tri = vertices[faces]  # (F, 3, 3)
    i_lo = np.clip(np.ceil((tri[:, :, 0].min(1) - xmin) / dx - 1e-9), 0, nx - 1).astype(np.int64)
    i_hi = np.clip(np.floor((tri[:, :, 0].max(1) - xmin) / dx + 1e-9), 0, nx - 1).astype(np.int64)
    j_lo = np.clip(np.ceil((tri[:, :, 1].min(1) - ymin) / dy - 1e-9), 0, ny - 1).astype(np.int64)
    j_hi = np.clip(np.floor((tri[:, :, 1].max(1) - ymin) / dy + 1e-9), 0, ny - 1).astype(np.int64)
    width = np.maximum(i_hi - i_lo + 1, 0)
    count = width * np.maximum(j_hi - j_lo + 1, 0)
    owner = np.repeat(np.arange(len(tri)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    ii = i_lo[owner] + local % width[owner]
    jj = j_lo[owner] + local // width[owner]
    px, py = xmin + ii * dx, ymin + jj * dy
    a, b, c = tri[owner, 0], tri[owner, 1], tri[owner, 2]
    den = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        wb = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (py - a[:, 1]) * (c[:, 0] - a[:, 0])) / den
        wc = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (b[:, 1] - a[:, 1]) * (px - a[:, 0])) / den
    wa = 1.0 - wb - wc
    tol = -1e-9
    inside = (np.abs(den) > 1e-18) & (wa >= tol) & (wb >= tol) & (wc >= tol)
    z = wa * a[:, 2] + wb * b[:, 2] + wc * c[:, 2]
    grid = np.full(ny * nx, -np.inf)
    np.maximum.at(grid, (jj * nx + ii)[inside], z[inside])
    grid = grid.reshape(ny, nx)
    empty = ~np.isfinite(grid)
    if empty.all():
        return np.zeros(shape)
    if empty.any():
        nearest = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
        grid = grid[tuple(nearest)]
    return grid


def check_assets(spec: DatasetSpec) -> dict[str, str]:
    """Fail before any rendering if a user mesh or texture named by the spec cannot be used.

    Returns the sha256 of each local user file by the spec field that names it.
    """
    files = {}
    for field, ref in spec.file_refs():
        if ref.path is None:
            continue
        if field in ("terrain.texture", "terrain.normal_map", "terrain.height_map"):
            # Decoded, not only read: a bad image fails here, not at a frame.
            files[field] = load_user_texture(Path(ref.path)).sha256
        elif field == "terrain.mesh":
            files[field] = load_user_terrain(Path(ref.path)).sha256
        else:
            files[field] = load_user_asset(Path(ref.path)).sha256
    return files
