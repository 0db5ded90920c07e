"""The GL renderer's framebuffers: built by kind and size, a few of each kind cached, deleted with their attachments."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from seasynth.service.errors import RenderError


@dataclass
class Target:
    """A framebuffer and its attachments, keyed by what it holds."""

    fbo: int
    textures: list[int] = field(default_factory=list)
    renderbuffers: list[int] = field(default_factory=list)


class Targets:
    """The framebuffers of one GL context, keyed by (kind, size, ...) and bounded to per_kind of each kind.

    The least recently used of a kind goes first, with every GL object it holds; asked for again, it is built from
    scratch. Every call needs the context current. gl: the PyOpenGL `GL` module; renderer_name names the GL
    renderer in errors.
    """

    def __init__(self, gl, renderer_name: str, per_kind: int) -> None:
        self._gl = gl
        self._renderer_name = renderer_name
        self.per_kind = per_kind
        self.cache: OrderedDict[tuple, Target] = OrderedDict()  # least recently used first

    def get(self, key: tuple, build: Callable[[], Target]) -> Target:
        """The cached framebuffer `key` (kind, size, ...), built and bound by `build` when absent."""
        got = self.cache.get(key)
        if got is not None:
            self.cache.move_to_end(key)
            return got
        got = build()
        GL = self._gl
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            self._delete(got)
            raise RenderError(f"framebuffer {key} incomplete on {self._renderer_name} (status {status:#x})")
        self.cache[key] = got
        same_kind = [k for k in self.cache if k[0] == key[0]]
        for old in same_kind[: max(len(same_kind) - self.per_kind, 0)]:
            self._drop(old)
        return got

    def clear(self) -> None:
        """Delete every cached framebuffer."""
        for key in list(self.cache):
            self._drop(key)

    def _drop(self, key: tuple) -> None:
        self._delete(self.cache.pop(key))

    def _delete(self, t: Target) -> None:
        GL = self._gl
        GL.glDeleteFramebuffers(1, [t.fbo])
        if t.textures:
            GL.glDeleteTextures(t.textures)
        if t.renderbuffers:
            GL.glDeleteRenderbuffers(len(t.renderbuffers), t.renderbuffers)

    def new_fbo(self) -> Target:
        """A new framebuffer with no attachments yet, bound (for a `build` to attach to)."""
        GL = self._gl
        t = Target(fbo=GL.glGenFramebuffers(1))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, t.fbo)
        return t

    def _attach_texture(self, t: Target, slot: int, fmt: int, w: int, h: int, samples: int,
                        attachment: int | None = None) -> None:
        """A new texture as colour attachment `slot` (or at `attachment`, e.g. GL_DEPTH_ATTACHMENT; slot is then its
        place in t.textures). The active texture unit keeps what was bound to it: a target built between binding a
        pass's inputs and drawing must not replace one of them."""
        GL = self._gl
        tex = GL.glGenTextures(1)
        if samples > 1:
            target, binding = GL.GL_TEXTURE_2D_MULTISAMPLE, GL.GL_TEXTURE_BINDING_2D_MULTISAMPLE
        else:
            target, binding = GL.GL_TEXTURE_2D, GL.GL_TEXTURE_BINDING_2D
        before = int(GL.glGetIntegerv(binding))
        GL.glBindTexture(target, tex)
        if samples > 1:
            GL.glTexImage2DMultisample(target, samples, fmt, w, h, GL.GL_TRUE)
        else:
            GL.glTexStorage2D(target, 1, fmt, w, h)
            GL.glTexParameteri(target, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(target, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glBindTexture(target, before)
        where = GL.GL_COLOR_ATTACHMENT0 + slot if attachment is None else attachment
        GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, where, target, tex, 0)
        t.textures.append(tex)

    def _attach_renderbuffer(self, t: Target, attachment: int, fmt: int, w: int, h: int, samples: int) -> None:
        GL = self._gl
        rb = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb)
        if samples > 1:
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, samples, fmt, w, h)
        else:
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, w, h)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, attachment, GL.GL_RENDERBUFFER, rb)
        t.renderbuffers.append(rb)

    def surface(self, w: int, h: int, msaa: int, with_range: bool) -> Target:
        """The surface pass's: colour (RGBA16F, slot 0) of msaa samples a pixel, and depth (32-bit float): a texture
        with range (the resolve derives each sample's range, and where anything was drawn, from it), else a
        renderbuffer."""

        def build() -> Target:
            GL = self._gl
            t = self.new_fbo()
            self._attach_texture(t, 0, GL.GL_RGBA16F, w, h, msaa)
            if with_range:
                self._attach_texture(t, 1, GL.GL_DEPTH_COMPONENT32F, w, h, msaa, attachment=GL.GL_DEPTH_ATTACHMENT)
            else:
                self._attach_renderbuffer(t, GL.GL_DEPTH_ATTACHMENT, GL.GL_DEPTH_COMPONENT32F, w, h, msaa)
            return t

        return self.get(("surface", w, h, msaa, with_range), build)

    def resolve(self, w: int, h: int, formats: tuple[int, ...]) -> Target:
        """One single-sample colour texture per output, in slot order (GL internal formats): drawn into by the
        fragment resolve, written as images by the compute resolve, read back through the framebuffer."""

        def build() -> Target:
            t = self.new_fbo()
            for slot, fmt in enumerate(formats):
                self._attach_texture(t, slot, fmt, w, h, 1)
            return t

        return self.get(("resolve", w, h, formats), build)

    def stencil(self, w: int, h: int) -> Target:
        """Single-sample depth and stencil, no colour: coverage counts (seasynth.worker.render.coverage)."""

        def build() -> Target:
            GL = self._gl
            t = self.new_fbo()
            self._attach_renderbuffer(t, GL.GL_DEPTH_STENCIL_ATTACHMENT, GL.GL_DEPTH24_STENCIL8, w, h, 1)
            GL.glDrawBuffers([GL.GL_NONE])
            GL.glReadBuffer(GL.GL_NONE)
            return t

        return self.get(("stencil", w, h), build)

    def ids(self, w: int, h: int, with_ids: bool, with_range: bool) -> Target:
        """Single-sample ids (slot 0, when drawn) and/or range (the next slot) at pixel centres, and depth."""

        def build() -> Target:
            GL = self._gl
            t = self.new_fbo()
            formats = [GL.GL_R32UI] * with_ids + [GL.GL_R32F] * with_range
            for slot, fmt in enumerate(formats):
                self._attach_renderbuffer(t, GL.GL_COLOR_ATTACHMENT0 + slot, fmt, w, h, 1)
            self._attach_renderbuffer(t, GL.GL_DEPTH_ATTACHMENT, GL.GL_DEPTH_COMPONENT32F, w, h, 1)
            return t

        return self.get(("ids", w, h, with_ids, with_range), build)
