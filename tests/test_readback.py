"""Reads through pixel buffer objects (seasynth.worker.render.readback): queued without a wait, fetched in any order, the
same pixels as a direct read, buffers reused and bounded, and given back when a frame fails before fetching."""

from __future__ import annotations

import numpy as np
import pytest
from test_render import LIGHT, camera_view, draw, fronto_quad, pinhole

from seasynth.worker.frame.function import PRESETS
from seasynth.worker.render import Passes
from seasynth.worker.render.readback import KEEP_PER_SIZE, KEEP_SIZES

W, H = 13, 7  # rows of 13 RGB bytes: not a multiple of 4, so a wrong pack alignment would show


def filled_target(renderer, values: list[float]):
    """A resolve-kind target of three float slots, each cleared to its value in every channel."""
    GL = renderer._gl
    renderer._platform.make_current()  # other tests' renderers may have made their own context current
    t = renderer.targets.resolve(W, H, (GL.GL_RGBA32F, GL.GL_RGBA8, GL.GL_R32F))
    GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, t.fbo)
    GL.glDrawBuffers([GL.GL_COLOR_ATTACHMENT0 + slot for slot in range(len(values))])
    for slot, v in enumerate(values):
        GL.glClearBufferfv(GL.GL_COLOR, slot, np.array([v, v / 2, v / 4, 1.0], np.float32))
    return t


def direct_read(GL, slot: int, fmt: int, typ: int, dtype, channels: int) -> np.ndarray:
    """glReadPixels into memory: a wait for the GPU, no buffer object."""
    GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0 + slot)
    arr = np.frombuffer(GL.glReadPixels(0, 0, W, H, fmt, typ), dtype=dtype)
    return arr.reshape(H, W, channels) if channels > 1 else arr.reshape(H, W)


def test_queued_reads_fetched_in_any_order_equal_direct_reads(renderer):
    GL = renderer._gl
    rb = renderer.readback
    filled_target(renderer, [0.75, 0.8, 3.25])
    reads = [(0, GL.GL_RGB, GL.GL_FLOAT, np.float32, 3), (1, GL.GL_RGB, GL.GL_UNSIGNED_BYTE, np.uint8, 3),
             (2, GL.GL_RED, GL.GL_FLOAT, np.float32, 1)]
    direct = [direct_read(GL, slot, fmt, typ, dt, ch) for slot, fmt, typ, dt, ch in reads]
    queued = [rb.queue(slot, W, H, fmt, typ, dt, ch) for slot, fmt, typ, dt, ch in reads]
    fetched = [rb.fetch(q) for q in reversed(queued)][::-1]
    for want, got in zip(direct, fetched):
        assert got.dtype == want.dtype and got.shape == want.shape
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(fetched[0][0, 0], [0.75, 0.375, 0.1875])
    np.testing.assert_array_equal(fetched[1], np.broadcast_to(np.array([204, 102, 51], np.uint8), (H, W, 3)))
    np.testing.assert_array_equal(fetched[2], np.full((H, W), 3.25, np.float32))


def quad_frame(renderer, key: str, instance_id: int):
    """A function rendering one 32x24 frame of a quad (8-bit image, ids and range: five reads)."""
    K = pinhole(32, 24, 60.0)
    view = camera_view(K, 32, 24)
    item = draw(key, fronto_quad(K, (4.5, 20.5), (3.5, 15.5), 5.0), instance_id)
    return lambda: renderer.render(view, [item], LIGHT, None, PRESETS["default"],
                                   Passes(ids=True, range=True, srgb8=True))


def test_a_frame_waits_once_and_its_buffers_are_reused(renderer):
    frame = quad_frame(renderer, "test/readback/quad", 7)
    first = frame()
    alive = renderer.readback.buffers
    for _ in range(3):
        again = frame()
        assert renderer.readback.buffers == alive  # the same buffers, none left queued
    for name in ("image", "instance", "range_m"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name), err_msg=name)
    assert set(np.unique(first.instance)) == {0, 7}


def test_buffers_of_many_sizes_stay_bounded(renderer):
    rb = renderer.readback
    item_key = "test/readback/sizes"
    for w in range(20, 20 + 3 * KEEP_SIZES):
        K = pinhole(w, 12, 60.0)
        item = draw(item_key, fronto_quad(pinhole(20, 12, 60.0), (2.5, 10.5), (2.5, 8.5), 5.0), 3)
        renderer.render(camera_view(K, w, 12), [item], LIGHT, None, PRESETS["draft"], Passes(ids=True, srgb8=True))
    # a frame of 8-bit image, NaN flags and ids reads three sizes of buffer; KEEP_SIZES sizes are kept
    assert rb.buffers <= KEEP_SIZES * KEEP_PER_SIZE
    assert len(rb._free) <= KEEP_SIZES


def test_a_frame_that_fails_after_queueing_its_reads_gives_their_buffers_back(renderer, monkeypatch):
    frame = quad_frame(renderer, "test/readback/fail", 5)
    good = frame()
    alive = renderer.readback.buffers
    real = renderer._queue_ids

    def queue_then_fail(*a, **k):
        real(*a, **k)  # the frame's image, NaN flag, nearest range, ids and centre range are all queued now
        raise RuntimeError("GL error after the reads were queued")

    monkeypatch.setattr(renderer, "_queue_ids", queue_then_fail)
    for _ in range(2 * KEEP_PER_SIZE):
        with pytest.raises(RuntimeError, match="after the reads were queued"):
            frame()
        assert renderer.readback.queued == 0
    assert renderer.readback.buffers == alive  # reused, not one more per failed frame
    monkeypatch.undo()
    again = frame()
    for name in ("image", "instance", "range_m"):
        np.testing.assert_array_equal(getattr(again, name), getattr(good, name), err_msg=name)


def test_two_frames_in_flight_give_what_each_frame_gives_alone(renderer):
    """GLRenderer.queue draws a frame and queues its reads; a second frame can be queued before the first is
    fetched (the GPU then never waits for the process), and each fetch gives exactly what render() gives."""
    args = []
    quads = (("test/readback/inflight-a", 3, (4.5, 20.5)), ("test/readback/inflight-b", 9, (2.5, 9.5)))
    for key, instance_id, x in quads:
        K = pinhole(32, 24, 60.0)
        args.append((camera_view(K, 32, 24), [draw(key, fronto_quad(K, x, (3.5, 15.5), 5.0), instance_id)], LIGHT,
                     None, PRESETS["default"], Passes(ids=True, range=True, srgb8=True)))
    alone = [renderer.render(*a) for a in args]
    first, second = (renderer.queue(*a) for a in args)
    assert renderer.readback.queued == 2 * 5  # each frame: 8-bit image, NaN flags, nearest range, ids, centre range
    got = [renderer.fetch(first), renderer.fetch(second)]
    assert renderer.readback.queued == 0
    for want, have in zip(alone, got):
        assert have.passes == want.passes
        for name in ("image", "instance", "range_m"):
            np.testing.assert_array_equal(getattr(have, name), getattr(want, name), err_msg=name)
    assert not np.array_equal(got[0].instance, got[1].instance)  # two different frames, not one fetched twice
