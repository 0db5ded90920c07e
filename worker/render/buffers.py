"""Meshes on the GPU: a Mesh's vertex attributes interleaved in one buffer and its faces in another, under a vertex
array (GLRenderer.mesh keeps them by key)."""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

from seasynth.worker.render import Mesh


@dataclass
class GpuMesh:
    """A Mesh on the GPU (GLRenderer.mesh): bind vao and draw count GL_UNSIGNED_INT indices as triangles."""

    vao: int
    buffers: tuple[int, int]  # vertex and index buffer
    count: int  # indices
    nbytes: int  # both buffers' sizes
    used: int  # the renderer call that last drew it


def upload_mesh(GL, mesh: Mesh, call: int) -> GpuMesh:
    """Upload a mesh (the context current): attributes 0, 1, 2 its vertices, normals and albedo; with texture
    coordinates, 3 and 4 those and its tangents (worker.render.materials, mapping "uv")."""
    columns = [mesh.vertices, mesh.normals, mesh.albedo]
    sizes = [3, 3, 3]
    if mesh.uv is not None:  # attributes 3 and 4: texture coordinates and tangents (materials mapping "uv")
        tangents = mesh.tangents if mesh.tangents is not None else np.zeros((len(mesh.vertices), 4), np.float32)
        columns += [mesh.uv, tangents]
        sizes += [2, 4]
    interleaved = np.ascontiguousarray(np.hstack(columns), dtype=np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    vao = GL.glGenVertexArrays(1)
    vbo, ebo = GL.glGenBuffers(2)
    GL.glBindVertexArray(vao)
    GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
    GL.glBufferData(GL.GL_ARRAY_BUFFER, interleaved.nbytes, interleaved, GL.GL_STATIC_DRAW)
    stride, offset = 4 * sum(sizes), 0
    for loc, size in enumerate(sizes):
        GL.glEnableVertexAttribArray(loc)
        GL.glVertexAttribPointer(loc, size, GL.GL_FLOAT, GL.GL_FALSE, stride, ctypes.c_void_p(offset))
        offset += 4 * size
    GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
    GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, faces.nbytes, faces, GL.GL_STATIC_DRAW)
    GL.glBindVertexArray(0)
    got = GpuMesh(vao=vao, buffers=(vbo, ebo), count=int(faces.size),
                  nbytes=interleaved.nbytes + faces.nbytes, used=call)
    return got
