"""Tests of what the GL renderer draws, reads back and keeps: frustum culling, pass skipping, bounded caches."""

import numpy as np
import pytest
import trimesh
from test_render import LIGHT, WATER, camera_view, draw, fronto_quad, pinhole

from seasynth.service.errors import RenderError
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS
from seasynth.worker.render import Passes, Sampling, View
from seasynth.worker.render.frustum import sphere_in_view
from seasynth.worker.render.gl import GLRenderer

W, H = 9, 7
K = pinhole(W, H, 60.0)
VIEW = camera_view(K, W, H)


@pytest.fixture
def draws(renderer, monkeypatch):
    """Counts the renderer's mesh draw calls (the resolve pass draws no mesh: it uses glDrawArrays)."""
    calls = []
    gl = renderer._gl
    real = gl.glDrawElements
    monkeypatch.setattr(gl, "glDrawElements", lambda *args: (calls.append(args), real(*args))[1])
    return calls


# --- frustum culling ----------------------------------------------------------------------------------------------


def test_an_object_whose_centre_is_outside_the_view_but_part_of_it_inside_is_drawn_and_has_its_pixels(renderer, draws):
    # The quad's image spans u in [-12.5, 2.5]: its centre (u = -5) is off the image, columns 0..2 are on it.
    quad = fronto_quad(K, (-12.5, 2.5), (1.5, 4.5), 5.0)
    item = draw("test/render-resources/half-outside", quad, 4)
    centre_u = K[0, 0] * item.mesh.centre[0] / item.mesh.centre[2] + K[0, 2]
    assert centre_u < -0.5
    result = renderer.render(VIEW, [item], LIGHT, WATER, PRESETS["default"], Passes(ids=True, range=True))
    expected = np.zeros((H, W), np.uint32)
    expected[2:5, 0:3] = 4
    np.testing.assert_array_equal(result.instance, expected)
    assert np.all(np.isfinite(result.range_m[2:5, 0:3]))
    assert renderer.pixels_alone(VIEW, item) == 9
    assert len(draws) == 3  # surface, ids, and alone


@pytest.mark.parametrize(
    "where",
    ["left", "right", "above", "below", "behind", "beyond-far"],
)
def test_an_object_wholly_outside_the_view_is_not_drawn(renderer, draws, where):
    u, v, z = {
        "left": ((-30.5, -10.5), (1.5, 4.5), 5.0),
        "right": ((20.5, 40.5), (1.5, 4.5), 5.0),
        "above": ((2.5, 5.5), (-30.5, -10.5), 5.0),
        "below": ((2.5, 5.5), (20.5, 40.5), 5.0),
        "behind": ((2.5, 5.5), (1.5, 4.5), -5.0),
        "beyond-far": ((2.5, 5.5), (1.5, 4.5), 50.0),
    }[where]
    outside = draw(f"test/render-resources/outside/{where}", fronto_quad(K, u, v, z), 5)
    inside = draw("test/render-resources/inside", fronto_quad(K, (2.5, 5.5), (1.5, 4.5), 5.0), 6)
    view = camera_view(K, W, H, near=0.1, far=20.0)
    result = renderer.render(view, [outside, inside], LIGHT, WATER, PRESETS["default"], Passes(ids=True))
    assert set(np.unique(result.instance)) == {0, 6}
    assert len(draws) == 2  # the inside quad, once per pass
    assert renderer.pixels_alone(view, outside) == 0 and len(draws) == 2


def test_sphere_in_view_is_false_only_beyond_a_radius_outside_a_plane():
    view = View(K=K, width=W, height=H, cam_from_world=np.eye(4), near=0.1, far=20.0)
    # The left image border (u = -0.5) is the plane through the origin with unit normal n (pointing inside).
    n = np.array([K[0, 0], 0.0, K[0, 2] + 0.5])
    n /= np.linalg.norm(n)
    on_border = np.array([(-0.5 - K[0, 2]) * 5.0 / K[0, 0], 0.0, 5.0])
    for d, radius, seen in [(-0.9, 1.0, True), (-1.1, 1.0, False), (0.0, 0.0, True), (-1e-6, 0.0, False)]:
        assert sphere_in_view(view, on_border + d * n, radius) is seen, (d, radius)
    assert sphere_in_view(view, np.array([0.0, 0.0, -0.85]), 1.0) is True  # reaches past the near plane (0.1)
    assert sphere_in_view(view, np.array([0.0, 0.0, -0.95]), 1.0) is False
    assert sphere_in_view(view, np.array([0.0, 0.0, 20.9]), 1.0) is True
    assert sphere_in_view(view, np.array([0.0, 0.0, 21.1]), 1.0) is False


# --- pass skipping ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "water, passes, expected",
    [
        (True, Passes(), ("surface+range", "resolve+haze", "read image")),
        (False, Passes(), ("surface", "resolve", "read image")),
        (True, Passes(clean=True), ("surface+range", "resolve+haze", "read image", "read clean")),
        (False, Passes(clean=True), ("surface", "resolve", "read image", "read clean")),
        (True, Passes(ids=True), ("surface+range", "resolve+haze", "read image", "ids", "read ids")),
        # Range: the surface pass's samples give the nearest hit; with several samples per pixel a single-sample
        # pass adds the pixel centres (with the ids when those are drawn too).
        (True, Passes(range=True), {
            "draft": ("surface+range", "resolve+haze", "read image", "read nearest range"),
            "high": ("surface+range", "resolve+haze", "read image", "read nearest range", "range", "read range"),
        }),
        (False, Passes(range=True), {
            "draft": ("surface+range", "resolve", "read image", "read nearest range"),
            "high": ("surface+range", "resolve", "read image", "read nearest range", "range", "read range"),
        }),
        (True, Passes(clean=True, ids=True, range=True), {
            "draft": ("surface+range", "resolve+haze", "read image", "read clean", "read nearest range", "ids",
                      "read ids"),
            "high": ("surface+range", "resolve+haze", "read image", "read clean", "read nearest range", "ids+range",
                     "read ids", "read range"),
        }),
    ],
)
@pytest.mark.parametrize("preset", ["draft", "high"])
def test_only_the_passes_asked_for_are_drawn_and_read(renderer, water, passes, expected, preset):
    item = draw("test/render-resources/inside", fronto_quad(K, (2.5, 5.5), (1.5, 4.5), 5.0), 6)
    result = renderer.render(VIEW, [item], LIGHT, WATER if water else None, PRESETS[preset], passes)
    assert result.passes == (expected[preset] if isinstance(expected, dict) else expected)
    assert (result.clean is not None) == passes.clean
    assert (result.instance is not None) == passes.ids
    assert (result.range_m is not None) == passes.range


OUTPUTS = ("labels", "meta", "depth", "instance", "clean", "range")
SURFACE = ("surface+range", "resolve+water", "read image srgb8")  # no noise: the codes come from the GPU


@pytest.mark.parametrize(
    "outputs, water, expected, alone",
    [
        ((), True, SURFACE, False),
        (("meta",), True, SURFACE, False),
        (("labels",), True, (*SURFACE, "ids", "read ids"), True),
        (("depth",), True, (*SURFACE, "read nearest range", "range", "read range"), False),
        (("instance",), True, (*SURFACE, "ids", "read ids"), False),
        (("clean",), True, (*SURFACE, "read clean"), False),
        (("range",), True, (*SURFACE, "read nearest range", "range", "read range"), False),
        (("clean", "range"), True, (*SURFACE, "read clean", "read nearest range", "range", "read range"), False),
        (("labels", "depth"), True, (*SURFACE, "read nearest range", "ids+range", "read ids", "read range"), True),
        (("labels", "meta"), False, ("surface", "resolve", "read image srgb8", "ids", "read ids"), True),
        ((), False, ("surface", "resolve", "read image srgb8"), False),
    ],
    ids=["image-only", "meta", "labels", "depth", "instance", "clean", "range", "clean+range", "labels+depth",
         "labels-dry", "dry"],
)
def test_each_output_configuration_draws_and_reads_back_only_what_its_files_need(
    render_session, monkeypatch, outputs, water, expected, alone
):
    renderer = render_session.renderer
    results, alone_calls = [], []
    render, pixels_alone = renderer.render, renderer.pixels_alone_many
    monkeypatch.setattr(renderer, "render", lambda *a, **k: results.append(render(*a, **k)) or results[-1])
    monkeypatch.setattr(renderer, "pixels_alone_many",
                        lambda view, jobs: alone_calls.extend(jobs) or pixels_alone(view, jobs))
    overrides = {f"outputs.{o}": o in outputs for o in OUTPUTS}
    spec = load_spec("examples/urchins.yaml", {"camera.width": 48, "camera.height": 36, "water.enabled": water,
                                               **overrides})
    render_session.frame_files(spec, 2)
    assert [r.passes for r in results] == [expected]
    # Labels also measure each labelled target alone (occlusion); nothing else does.
    assert bool(alone_calls) == alone


# --- bounded caches ----------------------------------------------------------------------------------------------


def gl_objects_exist(renderer, target) -> list[bool]:
    GL = renderer._gl
    return [bool(GL.glIsFramebuffer(target.fbo))] + [bool(GL.glIsTexture(t)) for t in target.textures] + [
        bool(GL.glIsRenderbuffer(r)) for r in target.renderbuffers
    ]


def test_framebuffers_are_kept_a_few_per_kind_and_evicted_ones_are_deleted(renderer):
    renderer._platform.make_current()
    n = renderer.targets.per_kind
    sizes = [(11 + i, 5) for i in range(n + 2)]
    built = []
    for i, (w, h) in enumerate(sizes):
        built.append(renderer.targets.ids(w, h, True, False))
        assert all(gl_objects_exist(renderer, built[-1]))
        ids_keys = [k for k in renderer.targets.cache if k[0] == "ids"]
        assert len(ids_keys) <= n and ("ids", w, h, True, False) in ids_keys
        if i >= n:
            # The least recently used is gone, with every GL object it held (checked at once: a driver may hand its
            # names out again to the next objects made).
            assert ("ids", *sizes[i - n], True, False) not in renderer.targets.cache
            assert not any(gl_objects_exist(renderer, built[i - n]))
    for t in built[2:]:
        assert all(gl_objects_exist(renderer, t))
    # Using one moves it to the back of the queue.
    assert renderer.targets.ids(*sizes[2], True, False) is built[2]
    renderer.targets.ids(40, 5, True, False)
    assert ("ids", *sizes[2], True, False) in renderer.targets.cache
    assert ("ids", *sizes[3], True, False) not in renderer.targets.cache


def test_a_frame_after_its_framebuffers_were_evicted_has_the_same_pixels(renderer):
    item = draw("test/render-resources/inside", fronto_quad(K, (2.5, 5.5), (1.5, 4.5), 5.0), 6)
    passes = Passes(clean=True, ids=True, range=True)
    first = renderer.render(VIEW, [item], LIGHT, WATER, PRESETS["high"], passes)
    for w in range(W + 1, W + 2 + renderer.targets.per_kind):  # other sizes push every target of VIEW out
        renderer.render(camera_view(pinhole(w, H, 60.0), w, H), [item], LIGHT, WATER, PRESETS["high"], passes)
    # (render draws no coverage counts: an earlier test's stencil target of this size may stay)
    assert not any(k[1:3] == (W * 2, H * 2) or k[1:3] == (W, H) for k in renderer.targets.cache if k[0] != "stencil")
    again = renderer.render(VIEW, [item], LIGHT, WATER, PRESETS["high"], passes)
    for name in ("image", "clean", "instance", "range_m"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name), err_msg=name)
    for kind in ("surface", "resolve", "ids"):
        assert len([k for k in renderer.targets.cache if k[0] == kind]) <= renderer.targets.per_kind


def box_item(key: str, offset_x: float, instance_id: int, subdivisions: int = 0):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.6)
    mesh.visual.vertex_colors = np.tile([180, 140, 90, 255], (len(mesh.vertices), 1))
    pose = np.eye(4)
    pose[:3, 3] = [offset_x, 0.0, 5.0]
    return draw(key, mesh, instance_id, pose)


def mesh_objects_exist(renderer, gpu) -> list[bool]:
    GL = renderer._gl
    return [bool(GL.glIsVertexArray(gpu.vao))] + [bool(GL.glIsBuffer(b)) for b in gpu.buffers]


def test_meshes_past_the_budget_are_evicted_least_recently_drawn_first_and_come_back_the_same(renderer, monkeypatch):
    a = box_item("test/render-resources/mesh-a", -1.0, 1)
    b = box_item("test/render-resources/mesh-b", 1.0, 2)
    c = box_item("test/render-resources/mesh-c", 0.0, 3, subdivisions=1)
    passes = Passes(ids=True, range=True)
    first = renderer.render(VIEW, [a], LIGHT, WATER, PRESETS["default"], passes)
    gpu_a = renderer._meshes[a.mesh.key]
    # Room for one of a and b, not both.
    monkeypatch.setattr(renderer, "mesh_budget_bytes", gpu_a.nbytes + 1)
    renderer.render(VIEW, [b], LIGHT, WATER, PRESETS["default"], passes)
    assert list(renderer._meshes) == [b.mesh.key]
    assert renderer._mesh_bytes == renderer._meshes[b.mesh.key].nbytes
    assert not any(mesh_objects_exist(renderer, gpu_a))
    # A frame that needs more than the budget keeps all its meshes until it is done...
    both = renderer.render(VIEW, [a, b], LIGHT, WATER, PRESETS["default"], passes)
    assert set(renderer._meshes) == {a.mesh.key, b.mesh.key} and renderer._mesh_bytes > renderer.mesh_budget_bytes
    assert set(np.unique(both.instance)) == {0, 1, 2}
    # ...and the next frame's upload evicts what it does not draw.
    renderer.render(VIEW, [c], LIGHT, WATER, PRESETS["default"], passes)
    assert list(renderer._meshes) == [c.mesh.key]
    again = renderer.render(VIEW, [a], LIGHT, WATER, PRESETS["default"], passes)
    for name in ("image", "instance", "range_m"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name), err_msg=name)


@pytest.mark.parametrize("kwargs", [{"mesh_budget_bytes": -1}, {"targets_per_kind": 0}])
def test_cache_bounds_are_checked_before_a_context_is_made(kwargs):
    with pytest.raises(RenderError, match=next(iter(kwargs))):
        GLRenderer(**kwargs)


def test_samples_are_the_same_after_their_framebuffers_were_evicted(renderer):
    item = draw("test/render-resources/inside", fronto_quad(K, (2.5, 5.5), (1.5, 4.5), 5.0), 6)
    J1, R1 = renderer.samples(VIEW, [item], LIGHT, Sampling(msaa=4))
    for w in range(W + 1, W + 2 + renderer.targets.per_kind):
        renderer.samples(camera_view(pinhole(w, H, 60.0), w, H), [item], LIGHT, Sampling(msaa=4))
    J2, R2 = renderer.samples(VIEW, [item], LIGHT, Sampling(msaa=4))
    np.testing.assert_array_equal(J1, J2)
    np.testing.assert_array_equal(R1, R2)


def test_sensor_noise_keeps_the_image_in_float_until_it_is_added(render_session, monkeypatch):
    renderer = render_session.renderer
    results = []
    render = renderer.render
    monkeypatch.setattr(renderer, "render", lambda *a, **k: results.append(render(*a, **k)) or results[-1])
    spec = load_spec("examples/urchins.yaml", {"camera.width": 48, "camera.height": 36, "outputs.labels": False,
                                               "noise.gaussian_sigma": 0.01})
    render_session.frame_files(spec, 2)
    assert [r.passes for r in results] == [SURFACE[:2] + ("read image",)]
    assert results[0].image.dtype == np.float32


def test_building_a_target_keeps_what_the_active_texture_unit_had_bound(renderer):
    """A target built after a pass bound its inputs (a new size, say) must not replace the input on that unit."""
    GL = renderer._gl
    renderer._platform.make_current()
    flat, multi = GL.glGenTextures(2)
    GL.glActiveTexture(GL.GL_TEXTURE0)
    GL.glBindTexture(GL.GL_TEXTURE_2D, flat)
    GL.glBindTexture(GL.GL_TEXTURE_2D_MULTISAMPLE, multi)
    try:
        renderer.targets.resolve(13, 3, (GL.GL_RGBA8, GL.GL_R8))
        renderer.targets.surface(13, 3, 4, True)
        assert int(GL.glGetIntegerv(GL.GL_TEXTURE_BINDING_2D)) == flat
        assert int(GL.glGetIntegerv(GL.GL_TEXTURE_BINDING_2D_MULTISAMPLE)) == multi
    finally:
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
        GL.glBindTexture(GL.GL_TEXTURE_2D_MULTISAMPLE, 0)
        GL.glDeleteTextures([flat, multi])
