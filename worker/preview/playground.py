"""The playground's renders: one frame of a spec at the `draft` preset with the views the page shows (image, depth,
instance ids, the clean image and the scene in air) and its label boxes; a strip of neighbouring thumbnails; and
the in-process previewer `seasynth playground` uses when no service runs."""

from __future__ import annotations

import base64
import io
import logging
import queue
import threading
import time
from collections.abc import Iterable
from concurrent.futures import Future

import numpy as np
from PIL import Image

from seasynth.service.kitti import parse_label_file
from seasynth.service.shards import frame_file, media_type
from seasynth.service.spec.dataset import DatasetSpec, parse_spec
from seasynth.worker.frame.function import RenderSession
from seasynth.worker.scene.sample import INPUT_ERRORS

log = logging.getLogger(__name__)

VIEWS = ("image", "depth", "instance", "clean", "air")
STRIP_WIDTH = 160  # thumbnails of the strip, pixels across


def preview_spec(spec: DatasetSpec, views: Iterable[str], width: int | None = None, labels: bool = True
                 ) -> DatasetSpec:
    """`spec` as the preview renders it: `draft`, labels as asked, the optional passes the views need, no exports, and
    (with `width`) a camera scaled to that width with its intrinsics scaled alike."""
    views = set(views)
    outputs = spec.outputs.model_copy(update={
        "labels": labels, "meta": False, "depth": "depth" in views, "instance": "instance" in views,
        "clean": "clean" in views, "range": False, "coco": False, "yolo": False, "mcap": False})
    camera = spec.camera
    if width is not None and width < camera.width:
        s = width / camera.width
        height = max(int(round(camera.height * s)), 8)
        update = {"width": width, "height": height}
        if camera.intrinsics is not None:
            k = camera.intrinsics
            update["intrinsics"] = k.model_copy(update={"fx": k.fx * s, "fy": k.fy * s, "cx": k.cx * s,
                                                        "cy": k.cy * s})
        camera = camera.model_copy(update=update)
    return spec.model_copy(update={"quality": "draft", "outputs": outputs, "camera": camera})


def png_data_url(png: bytes, mime: str = "image/png") -> str:
    return f"data:{mime};base64," + base64.b64encode(png).decode()


def image_data_url(files: dict[str, bytes], spec: DatasetSpec, index: int) -> str:
    """The frame's image_2 file (PNG or JPEG, as the spec writes it) as a data URL."""
    rel = frame_file("image", index, spec.outputs.image_suffix)
    return png_data_url(files[rel], media_type(rel))


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def depth_view(depth_png16: bytes) -> bytes:
    """The 16-bit depth PNG (z in m x 256, 0 where no surface) as 8-bit grey scaled to the frame's own depth span:
    the nearest surface white, the farthest dark grey (40), no surface black."""
    z = np.asarray(Image.open(io.BytesIO(depth_png16))).astype(np.float32)
    hit = z > 0
    out = np.zeros(z.shape, np.uint8)
    if hit.any():
        near, far = float(z[hit].min()), float(z[hit].max())
        out[hit] = (255 - 215 * (z[hit] - near) / max(far - near, 1.0)).astype(np.uint8)
    return _png(out)


def instance_view(instance_png16: bytes) -> bytes:
    """Instance ids as colours: each id a fixed colour (a hash of the id), the terrain (0) dark grey."""
    ids = np.asarray(Image.open(io.BytesIO(instance_png16))).astype(np.uint32)
    h = (ids * np.uint32(2654435761)) & np.uint32(0xFFFFFF)
    rgb = np.stack([(h >> 16) & 255, (h >> 8) & 255, h & 255], axis=-1).astype(np.uint8) | np.uint8(64)
    rgb[ids == 0] = 40
    return _png(rgb)


def render_preview(session: RenderSession, spec: DatasetSpec, frame: int, views: Iterable[str]) -> dict:
    """Frame `frame` of `spec` at `draft`: {"frame", "seed", "width", "height", "images": {view: data URL},
    "boxes": [{"class", "box": [left, top, right, bottom] (pixels, inclusive), "truncated", "occluded"}],
    "render_ms"}. Views outside VIEWS are refused by the caller's model."""
    views = [v for v in VIEWS if v in set(views) | {"image"}]
    t0 = time.perf_counter()
    spec = preview_spec(spec, views)
    files = session.frame_files(spec, frame)
    images = {"image": image_data_url(files, spec, frame)}
    if "depth" in views:
        images["depth"] = png_data_url(depth_view(files[frame_file("depth", frame)]))
    if "instance" in views:
        images["instance"] = png_data_url(instance_view(files[frame_file("instance", frame)]))
    if "clean" in views:
        images["clean"] = png_data_url(files[frame_file("clean", frame)])
    if "air" in views:
        air = spec.model_copy(update={"water": spec.water.model_copy(update={"enabled": False})})
        images["air"] = image_data_url(session.frame_files(air, frame), air, frame)
    boxes = [{"class": o["type"], "box": o["bbox"],
              "truncated": o["truncated"], "occluded": o["occluded"]}
             for o in parse_label_file(files[frame_file("label", frame)].decode())]
    return {"frame": frame, "seed": spec.seed, "width": spec.camera.width, "height": spec.camera.height,
            "images": images, "boxes": boxes, "render_ms": round((time.perf_counter() - t0) * 1000, 1)}


def render_strip(session: RenderSession, spec: DatasetSpec, first: int, count: int) -> dict:
    """Thumbnails (STRIP_WIDTH across) of frames first .. first+count-1: {"frames": [{"frame", "image"}]}."""
    small = preview_spec(spec, ["image"], width=STRIP_WIDTH, labels=False)
    out = []
    for i in range(first, first + count):
        files = session.frame_files(small, i)
        out.append({"frame": i, "image": image_data_url(files, small, i)})
    return {"frames": out}


class LocalPreviewer:
    """Renders previews in this process, on one thread that owns the GL context (a context is current on one
    thread only). Jobs run one at a time in arrival order; the page's latest-wins rule is the API's."""

    def __init__(self, platform: str = "egl") -> None:
        self._platform = platform
        self._jobs: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def __enter__(self) -> LocalPreviewer:
        self._thread = threading.Thread(target=self._run, name="seasynth-playground-gl", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error
        return self

    def __exit__(self, *exc: object) -> None:
        self._jobs.put(None)
        if self._thread is not None:
            self._thread.join(timeout=30)

    def _run(self) -> None:
        try:
            session = RenderSession(platform=self._platform).__enter__()
        except BaseException as err:  # reported to __enter__, which raises it in the caller
            self._error = err
            self._ready.set()
            return
        self._ready.set()
        try:
            while (job := self._jobs.get()) is not None:
                fn, args, fut = job
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn(session, *args))
                    except BaseException as err:  # handed to the waiting request, which answers it
                        fut.set_exception(err)
        finally:
            session.close()

    def _submit(self, fn, *args) -> dict:
        fut: Future = Future()
        self._jobs.put((fn, args, fut))
        return fut.result()

    def preview(self, spec: DatasetSpec, frame: int, views: list[str]) -> dict:
        return self._submit(render_preview, spec, frame, views)

    def strip(self, spec: DatasetSpec, first: int, count: int) -> dict:
        return self._submit(render_strip, spec, first, count)


def preview_reply(session: RenderSession, kind: str, spec_json: dict, args: list) -> tuple[dict, bytes]:
    """A frames-queue worker's answer to the API's preview request: (header, JSON body), or an error header
    with the status the API answers (422: the spec or its assets cannot render; 500: rendering failed)."""
    import json

    try:
        spec = parse_spec(spec_json)
        out = render_preview(session, spec, *args) if kind == "preview" else render_strip(session, spec, *args)
    except INPUT_ERRORS as err:
        return {"ok": False, "status": 422, "error": str(err)}, b""
    except Exception as err:  # reported to the page as a failed render; the worker goes on
        log.exception("playground %s failed", kind)
        return {"ok": False, "status": 500, "error": f"{type(err).__name__}: {err}"}, b""
    return {"ok": True}, json.dumps(out).encode()
