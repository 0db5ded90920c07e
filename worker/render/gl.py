"""Headless OpenGL renderer on pyrender's EGL/OSMesa platforms, with float framebuffers and our own shaders.

Why not pyrender's stock renderer: it writes gamma-encoded colour into an 8-bit 4x MSAA buffer (resolved in that
space), returns z-depth from one sample with 0 for no hit, and renders passes we may not need. Here colour stays
linear and float, range comes from each sample's reversed float depth (float32 precision at every range:
seasynth.worker.render.depth), open water is +inf, the water is applied per sample before averaging, and only the
passes a frame's outputs need are drawn and read back.
"""

from __future__ import annotations

import ctypes
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from seasynth.service.errors import RenderError
from seasynth.service.gpus import parse_platform
from seasynth.worker.render import (
    DrawItem,
    Lighting,
    Material,
    Mesh,
    Passes,
    RenderResult,
    Sampling,
    View,
    WaterParams,
    normal_matrix,
    shaders,
)
from seasynth.worker.render.buffers import GpuMesh, upload_mesh
from seasynth.worker.render.coverage import pixels_alone
from seasynth.worker.render.depth import ClipControl, projection
from seasynth.worker.render.devices import egl_platform, prepare_environment
from seasynth.worker.render.frustum import sphere_in_view
from seasynth.worker.render.materials import TEXTURE_BUDGET_BYTES, Textures
from seasynth.worker.render.programs import Programs
from seasynth.worker.render.readback import Pending, Readback
from seasynth.worker.render.surface import SurfaceReads, surface_pass
from seasynth.worker.render.targets import Target, Targets

# Cache bounds of a long-lived renderer. Uploaded meshes: least recently drawn first out once their vertex and index
# buffers pass the budget, never one drawn by the call in progress. Framebuffers: a few of each kind (surface,
# resolve, ids), least recently used first out; one frame uses at most two of a kind.
MESH_BUDGET_BYTES = 512 * 2**20
TARGETS_PER_KIND = 4


@dataclass(frozen=True)
class QueuedFrame:
    """A frame whose passes are drawn and reads queued (GLRenderer.queue), for GLRenderer.fetch."""

    reads: SurfaceReads
    ids: Pending | None  # instance ids at pixel centres
    centres: Pending | None  # range at pixel centres
    passes: tuple[str, ...]  # the passes drawn and attachments read, in order


class GLRenderer:
    """One OpenGL context per process. Meshes are uploaded once by key; framebuffers are reused by size
    (`targets`, seasynth.worker.render.targets); the surface pass and its resolve are worker.render.surface.

    The passes in sibling modules (surface, gl_light, coverage) draw through the public members only: `gl`,
    `programs`, `targets`, `textures`, `readback`, `mesh`, `draw`, `set_view`, `bind_and_clear`, `empty_vao`,
    `view_table_buffer` (the solved water's uniform block, gl_light's) and the context's facts (`name`,
    `max_samples`, `compute_resolve`, `compute_header`, `clip_control`, `sample_positions`).

    The caches are bounded (mesh_budget_bytes of vertex and index buffers, texture_budget_bytes of texture images
    with their mipmaps, targets_per_kind framebuffers of each kind), so a long-lived worker that meets many assets
    and image sizes does not keep them all; what is evicted is deleted and rebuilt from scratch when needed again,
    with the same pixels.
    """

    def __init__(
        self,
        platform: str = "egl",
        mesh_budget_bytes: int = MESH_BUDGET_BYTES,
        targets_per_kind: int = TARGETS_PER_KIND,
        gpu: int | None = None,
        texture_budget_bytes: int = TEXTURE_BUDGET_BYTES,
    ) -> None:
        platform, gpu = parse_platform(platform, gpu)
        if mesh_budget_bytes < 0:
            raise RenderError(f"mesh_budget_bytes must be >= 0, got {mesh_budget_bytes}")
        if targets_per_kind < 1:
            raise RenderError(f"targets_per_kind must be >= 1, got {targets_per_kind}")
        self.mesh_budget_bytes = mesh_budget_bytes
        self.gpu = gpu  # EGL device index; None: EGL's default device (or OSMesa)
        prepare_environment(platform)
        self._platform_name = platform
        try:
            if platform == "egl":
                self._platform = egl_platform(gpu)  # a missing device: RenderError naming it and the count
            else:
                from pyrender.platforms.osmesa import OSMesaPlatform  # after prepare_environment, as OpenGL

                self._platform = OSMesaPlatform(8, 8)
            self._platform.init_context()
            self._platform.make_current()
        except RenderError:
            raise
        except Exception as err:  # EGL/OSMesa report failures in many shapes; all mean "no context"
            raise RenderError(f"cannot create a headless {platform} OpenGL context: {err!r}") from err
        from OpenGL import GL  # only now: PyOpenGL picks its platform at its first import (prepare_environment)

        self._gl = GL
        self.name = GL.glGetString(GL.GL_RENDERER).decode()
        self.version = GL.glGetString(GL.GL_VERSION).decode()
        self.max_samples = int(GL.glGetIntegerv(GL.GL_MAX_SAMPLES))
        # The resolve runs as a compute shader on a GPU whose context has them (GL 4.3; shaders.RESOLVE): on an H100
        # it took the GPU 2.5 ms a 1080p frame as a fragment shader, which runs on few of its units. A software
        # rasteriser runs both kinds on the same cores, and its fragment path was the faster (llvmpipe, 640x480:
        # 33 against 39 ms). Both write the same bytes.
        software = any(k in self.name.lower() for k in ("llvmpipe", "softpipe", "swrast"))
        self.compute_header = None if software else shaders.compute_header(GL)
        self.compute_resolve = self.compute_header is not None
        self.textures = Textures(GL, self.name, texture_budget_bytes, anisotropic=not software)
        self._meshes: OrderedDict[str, GpuMesh] = OrderedDict()  # least recently drawn first
        self._mesh_bytes = 0
        self._call = 0  # counts render/samples/pixels_alone calls: meshes drawn by the current one stay
        self.programs = Programs(GL, self.name)
        self.targets = Targets(GL, self.name, targets_per_kind)
        self.readback = Readback(GL)
        self.empty_vao = GL.glGenVertexArrays(1)  # no attributes: what full-screen triangles (the resolve) draw with
        self.view_table_buffer: int | None = None  # the solved water's view table (gl_light), made on first use
        self.clip_control = ClipControl(GL, self.name)
        self.sample_positions: dict[int, np.ndarray] = {}  # msaa -> (msaa, 2), read once (seasynth.worker.render.depth)
        GL.glEnable(GL.GL_DEPTH_TEST)
        self.clip_control.camera()  # reversed depth for the camera's passes; shadow maps switch to GL's own
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)

    # ---- lifecycle -------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Release every GL object and the context. Safe to call twice."""
        if self._platform is None:
            return
        GL = self._gl
        self._platform.make_current()
        for key in list(self._meshes):
            self._drop_mesh(key)
        self.programs.clear()
        self.textures.clear()
        self.targets.clear()
        self.readback.clear()
        GL.glDeleteVertexArrays(1, [self.empty_vao])
        if self._platform_name == "egl":
            # Destroy only our context: pyrender's delete_context() also terminates the EGL display, which
            # every context of the process shares, and would kill other renderers that are still open.
            from OpenGL import EGL  # imported once the platform is chosen, as GL is (__init__)

            p = self._platform
            EGL.eglMakeCurrent(p._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
            EGL.eglDestroyContext(p._egl_display, p._egl_context)
        else:
            self._platform.delete_context()
        self._platform = None

    def __enter__(self) -> GLRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- what the passes draw with (surface, gl_light, coverage); each needs the context current --------------
    @property
    def gl(self):
        """The PyOpenGL `GL` module, for this renderer's context."""
        return self._gl

    def mesh(self, mesh: Mesh) -> GpuMesh:
        """The mesh on the GPU, uploaded on first use; kept at least until the current call (render, samples,
        geometry, pixels_alone_many) returns, then least recently drawn first out past mesh_budget_bytes."""
        got = self._meshes.get(mesh.key)
        if got is not None:
            got.used = self._call
            self._meshes.move_to_end(mesh.key)
            return got
        got = upload_mesh(self._gl, mesh, self._call)
        self._meshes[mesh.key] = got
        self._mesh_bytes += got.nbytes
        while self._mesh_bytes > self.mesh_budget_bytes:
            key, oldest = next(iter(self._meshes.items()))
            if oldest.used == self._call:
                break  # every mesh left is drawn by this call; the budget is met again after it
            self._drop_mesh(key)
        return got

    def _drop_mesh(self, key: str) -> None:
        GL = self._gl
        m = self._meshes.pop(key)
        self._mesh_bytes -= m.nbytes
        GL.glDeleteVertexArrays(1, [m.vao])
        GL.glDeleteBuffers(2, list(m.buffers))

    def draw(self, view: View, items: list[DrawItem], locs: dict[str, int], *, lit: bool, ids: bool,
             parts: list[tuple[int, int | None, Material | None]] | None = None) -> None:
        """Draw with the program in use (its uniform locations `locs`) each item whose bounding sphere reaches into
        the view, setting per item u_cam_from_obj (4x4, object frame -> camera frame, metres) and, where the program
        has them, u_range_bounds (its sphere's nearest and farthest range, metres); lit: its normal matrix and
        albedo scale and bias, and (textured programs) its material; ids: u_id, its instance id. parts (one per
        item): (first face, face count or None for the rest, material) to draw of it; None: every face with the
        mesh's material."""
        GL = self._gl
        cam_from_world = view.cam_from_world
        for k, item in enumerate(items):
            first, count, material = parts[k] if parts is not None else (0, None, item.mesh.material)
            cam_from_obj = cam_from_world @ item.world_from_obj
            centre_world, radius = item.bounding_sphere()
            centre = cam_from_world[:3, :3] @ centre_world + cam_from_world[:3, 3]
            if not sphere_in_view(view, centre, radius):
                continue
            gpu = self.mesh(item.mesh)
            if "u_range_bounds" in locs:
                dist = float(np.linalg.norm(centre))
                GL.glUniform2f(locs["u_range_bounds"], max(dist - radius, 0.0), dist + radius)
            GL.glUniformMatrix4fv(locs["u_cam_from_obj"], 1, GL.GL_TRUE, cam_from_obj.astype(np.float32))
            if lit and "u_nrm_cam" in locs:  # a frame with no light at all (sun down, no lamps) shades nothing
                GL.glUniformMatrix3fv(locs["u_nrm_cam"], 1, GL.GL_TRUE, normal_matrix(cam_from_obj[:3, :3]))
                GL.glUniform3fv(locs["u_scale"], 1, item.albedo_scale.astype(np.float32))
                GL.glUniform3fv(locs["u_bias"], 1, item.albedo_bias.astype(np.float32))
            if lit and "u_material" in locs:
                self.textures.bind(material, locs, self._call)
            if ids:
                GL.glUniform1ui(locs["u_id"], item.instance_id)
            GL.glBindVertexArray(gpu.vao)
            n = gpu.count - 3 * first if count is None else 3 * count
            GL.glDrawElements(GL.GL_TRIANGLES, n, GL.GL_UNSIGNED_INT, ctypes.c_void_p(12 * first) if first else None)
        GL.glBindVertexArray(0)

    def set_view(self, locs: dict[str, int], view: View, w: int, h: int) -> None:
        """Viewport (w, h) framebuffer pixels (the view's size times any supersampling) and u_proj: the view's
        reversed-depth projection (seasynth.worker.render.depth.projection), for the program in use."""
        GL = self._gl
        GL.glViewport(0, 0, w, h)
        proj = projection(view.K, view.width, view.height, view.near, view.far)
        GL.glUniformMatrix4fv(locs["u_proj"], 1, GL.GL_TRUE, proj.astype(np.float32))

    def bind_and_clear(self, t: Target, clears: tuple[str, ...]) -> None:
        """Bind a geometry target and draw into its colour attachments in slot order, each cleared as named:
        "ids" to 0, "colour" to 0, "range" to +inf, "keep" not at all (what the last frame left); depth to far
        (reversed depth's 0)."""
        GL = self._gl
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, t.fbo)
        GL.glDrawBuffers([GL.GL_COLOR_ATTACHMENT0 + slot for slot in range(len(clears))])
        for slot, what in enumerate(clears):
            if what == "keep":
                continue
            if what == "ids":
                GL.glClearBufferuiv(GL.GL_COLOR, slot, np.zeros(4, np.uint32))
            else:
                value = np.inf if what == "range" else 0.0
                GL.glClearBufferfv(GL.GL_COLOR, slot, np.array([value, 0, 0, 0], np.float32))
        GL.glClear(GL.GL_DEPTH_BUFFER_BIT)

    # ---- frames ----------------------------------------------------------------------------------------------
    def render(
        self,
        view: View,
        items: list[DrawItem],
        lighting: Lighting,
        water: WaterParams | None,
        sampling: Sampling,
        passes: Passes,
        mark: Callable[[str], None] | None = None,
    ) -> RenderResult:
        """Render one frame: linear hazed image, and the optional clean image, ids and range (queue, then fetch).

        Range (passes.range) is +inf exactly where none of the pixel's samples hits a surface (the pixel's colour
        is pure water); elsewhere the range at the pixel centre where the centre hits a surface, else the nearest
        range a sample hits. Where every sample lies at the pixel centre (one sample per pixel) the surface pass's
        own samples give it; otherwise a single-sample pass adds the centres.

        mark: called with a stage name when each stage's GL work has finished (benchmarks only: it waits).
        """
        stage = (lambda name: (self._gl.glFinish(), mark(name))) if mark is not None else None
        return self.fetch(self.queue(view, items, lighting, water, sampling, passes, stage=stage))

    def queue(
        self,
        view: View,
        items: list[DrawItem],
        lighting: Lighting,
        water: WaterParams | None,
        sampling: Sampling,
        passes: Passes,
        stage: Callable[[str], None] | None = None,
    ) -> QueuedFrame:
        """Draw every pass of a frame and queue its reads, without waiting for the GPU; `fetch` waits once and gives
        the RenderResult. Another frame may be queued before this one is fetched (benchmarks keep two in flight).

        stage: called with each stage's name ("render", "formation", "ids") once its GL commands are issued.
        """
        self._platform.make_current()
        self._call += 1
        done = stage if stage is not None else (lambda name: None)
        log: list[str] = []
        try:
            reads = surface_pass(self, view, items, lighting, water, sampling, want_clean=passes.clean,
                                 want_nearest=passes.range, srgb8=passes.srgb8, done=done, log=log)
            centres = passes.range and sampling.per_pixel > 1
            ids = self._queue_ids(view, items, passes.ids, centres, log=log) if passes.ids or centres else (None, None)
            done("ids")
        except BaseException:
            self.readback.abandon()
            raise
        return QueuedFrame(reads, ids[0], ids[1], tuple(log))

    def fetch(self, queued: QueuedFrame) -> RenderResult:
        """Wait for a queued frame's reads (one wait for the GPU: seasynth.worker.render.readback) and give its
        result. A failure gives back the buffers of every read still queued, this frame's and any other's."""
        self._platform.make_current()
        try:
            image, clean, nearest = queued.reads.fetch(self.readback)
            instance, centre = (None if q is None else self.readback.fetch(q) for q in (queued.ids, queued.centres))
        except BaseException:
            self.readback.abandon()
            raise
        # A sliver can cover a pixel centre and none of its samples: the image shows water there, so must range.
        range_m = nearest if centre is None else np.where(np.isfinite(centre) & np.isfinite(nearest), centre, nearest)
        return RenderResult(image=image, clean=clean, instance=instance, range_m=range_m, passes=queued.passes)

    def samples(
        self, view: View, items: list[DrawItem], lighting: Lighting, sampling: Sampling
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every sample of a frame, for audits: J (k, h, w, 3) float32 linear and range (k, h, w) float32."""
        self._platform.make_current()
        self._call += 1
        Js, Rs = [], []
        for k in range(sampling.per_pixel):
            J, R, _ = surface_pass(self, view, items, lighting, None, sampling, only_sample=k,
                                   sample_range=True).fetch(self.readback)
            Js.append(J)
            Rs.append(R[..., 0])
        return np.stack(Js), np.stack(Rs)

    def _ids(self, view: View, items: list[DrawItem], want_ids: bool, want_range: bool, log: list[str] | None = None):
        """Draw ids and/or range at pixel centres (one sample) and read them: (ids or None, range or None)."""
        return tuple(None if q is None else self.readback.fetch(q)
                     for q in self._queue_ids(view, items, want_ids, want_range, log))

    def _queue_ids(self, view: View, items: list[DrawItem], want_ids: bool, want_range: bool,
                   log: list[str] | None = None):
        """Draw ids and/or range at pixel centres and queue their reads (readback Pending or None each); log (if
        given) gets the pass and the reads."""
        GL = self._gl
        log = [] if log is None else log
        w, h = view.width, view.height
        t = self.targets.ids(w, h, want_ids, want_range)
        self.bind_and_clear(t, ("ids",) * want_ids + ("range",) * want_range)
        # ids at slot 0 and/or range at the slot after them, as targets.ids lays them out
        prog, locs = self.programs.get(shaders.VERTEX, shaders.IDS, WITH_IDS=want_ids, WITH_RANGE=want_range,
                                       RANGE_LOCATION=int(want_ids))
        GL.glUseProgram(prog)
        self.set_view(locs, view, w, h)
        self.draw(view, items, locs, lit=False, ids=want_ids)
        log.append("+".join(["ids"] * want_ids + ["range"] * want_range))
        ids = rng = None
        if want_ids:
            ids = self.readback.queue(0, w, h, GL.GL_RED_INTEGER, GL.GL_UNSIGNED_INT, np.uint32, 1)
            log.append("read ids")
        if want_range:
            rng = self.readback.queue(int(want_ids), w, h, GL.GL_RED, GL.GL_FLOAT, np.float32, 1)
            log.append("read range")
        return ids, rng

    def geometry(self, view: View, items: list[DrawItem]) -> tuple[np.ndarray, np.ndarray]:
        """First-hit instance ids (h, w) uint32 (0 = terrain or nothing) and range (h, w) float32 metres (+inf
        where nothing is hit) at pixel centres: what a non-optical sensor (sonar) needs, with no shading."""
        self._platform.make_current()
        self._call += 1
        return self._ids(view, items, True, True)

    def pixels_alone(self, view: View, item: DrawItem, region: tuple[int, int, int, int] | None = None) -> int:
        """Pixels (at pixel centres) the item covers when rendered with nothing else in the scene.

        region: (left, top, right, bottom) inclusive pixel bounds known to contain the item's projection;
        only that part of the framebuffer is cleared and drawn.
        """
        return self.pixels_alone_many(view, [(item, region)])[0]

    def pixels_alone_many(self, view: View, jobs: list[tuple[DrawItem, tuple[int, int, int, int] | None]]) -> list[int]:
        """pixels_alone of each (item, region), with one wait for the GPU (seasynth.worker.render.coverage)."""
        self._platform.make_current()
        self._call += 1
        return pixels_alone(self, view, jobs)
