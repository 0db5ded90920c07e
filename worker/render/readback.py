"""Reading attachments back through pixel buffer objects: a read is queued without waiting for the GPU, and the
frame's reads are fetched together after its last pass is queued, so a frame waits for the GPU once instead of once
a read (each wait on a GPU shared by many processes' contexts is a wait for this context's turn)."""

from __future__ import annotations

import ctypes
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np


@dataclass
class Pending:
    """A queued read: the buffer it lands in and the array it becomes."""

    pbo: int
    nbytes: int
    shape: tuple[int, ...]
    dtype: np.dtype


KEEP_SIZES = 4  # sizes whose free buffers are kept (a frame reads at most a few sizes; the playground changes size)
KEEP_PER_SIZE = 6  # free buffers kept of one size: a frame's reads of that size


class Readback:
    """The pixel buffer objects of one GL context, reused by size (a few sizes, a few of each: the rest are
    deleted). Every call needs the context current."""

    def __init__(self, gl) -> None:
        self._gl = gl
        self._free: OrderedDict[int, list[int]] = OrderedDict()  # by size, least recently used first
        self._all: set[int] = set()
        self._queued: dict[int, Pending] = {}  # reads queued and not yet fetched, by buffer

    def queue(self, slot: int, w: int, h: int, fmt: int, typ: int, dtype, channels: int, x: int = 0,
              y: int = 0) -> Pending:
        """Queue a read of colour attachment `slot` of the bound read framebuffer (rows in framebuffer order)."""
        from OpenGL.raw.GL.VERSION.GL_1_0 import glReadPixels  # here: PyOpenGL picks its platform at its first import

        GL = self._gl
        dtype = np.dtype(dtype)
        shape = (h, w, channels) if channels > 1 else (h, w)
        nbytes = w * h * channels * dtype.itemsize
        free = self._free.get(nbytes)
        if free:
            pbo = free.pop()
        else:
            pbo = int(GL.glGenBuffers(1))
            self._all.add(pbo)
            GL.glBindBuffer(GL.GL_PIXEL_PACK_BUFFER, pbo)
            GL.glBufferData(GL.GL_PIXEL_PACK_BUFFER, nbytes, None, GL.GL_STREAM_READ)
        GL.glBindBuffer(GL.GL_PIXEL_PACK_BUFFER, pbo)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0 + slot)
        glReadPixels(x, y, w, h, fmt, typ, ctypes.c_void_p(0))
        GL.glBindBuffer(GL.GL_PIXEL_PACK_BUFFER, 0)
        p = Pending(pbo, nbytes, shape, dtype)
        self._queued[pbo] = p
        return p

    def fetch(self, p: Pending) -> np.ndarray:
        """The read's pixels (waits for the GPU where it has not finished them); its buffer is reused."""
        GL = self._gl
        out = np.empty(p.shape, dtype=p.dtype)
        GL.glBindBuffer(GL.GL_PIXEL_PACK_BUFFER, p.pbo)
        ptr = GL.glMapBufferRange(GL.GL_PIXEL_PACK_BUFFER, 0, p.nbytes, GL.GL_MAP_READ_BIT)
        try:
            address = ptr if isinstance(ptr, int) else ctypes.cast(ptr, ctypes.c_void_p).value
            if not address:
                raise RuntimeError("glMapBufferRange returned no pointer for a pixel read")
            ctypes.memmove(out.ctypes.data, address, p.nbytes)
        finally:
            GL.glUnmapBuffer(GL.GL_PIXEL_PACK_BUFFER)
            GL.glBindBuffer(GL.GL_PIXEL_PACK_BUFFER, 0)
        self._release(p)
        return out

    def abandon(self) -> None:
        """Give back the buffers of every read queued and not fetched, unread: a frame that failed between queueing
        its reads and fetching them (a GL error, NaN in its image) must not keep them until the context closes."""
        for p in list(self._queued.values()):
            self._release(p)

    @property
    def queued(self) -> int:
        """Reads queued and not yet fetched (for tests)."""
        return len(self._queued)

    @property
    def buffers(self) -> int:
        """Buffers alive, queued reads' included (for tests)."""
        return len(self._all)

    def _release(self, p: Pending) -> None:
        self._queued.pop(p.pbo, None)
        free = self._free.setdefault(p.nbytes, [])
        self._free.move_to_end(p.nbytes)
        free.append(p.pbo)
        drop = free[KEEP_PER_SIZE:]
        del free[KEEP_PER_SIZE:]
        while len(self._free) > KEEP_SIZES:
            drop += self._free.popitem(last=False)[1]
        if drop:
            self._gl.glDeleteBuffers(len(drop), drop)
            self._all.difference_update(drop)

    def clear(self) -> None:
        """Delete every buffer."""
        if self._all:
            self._gl.glDeleteBuffers(len(self._all), list(self._all))
        self._all.clear()
        self._free.clear()
        self._queued.clear()
