"""Hard cases of geometry and labels through the renderer: borders, hidden and one-pixel targets, and degenerate
meshes (cameras drawn inside geometry: test_hard_cases_cameras.py)."""

import numpy as np
import pytest
import trimesh

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame import kitti, labels
from seasynth.worker.frame.function import PRESETS, to_render_mesh
from seasynth.worker.render import DrawItem, Lighting, Passes, View, WaterParams
from seasynth.worker.scene.assets import Asset
from seasynth.worker.scene.assets.terrain import procedural_terrain
from seasynth.worker.scene.sample import (
    Placed,
    Scene,
)

EXAMPLE = "examples/urchins.yaml"
LIGHT = Lighting(sun_dir_world=np.array([0.3, -0.8, -0.5]) / np.linalg.norm([0.3, -0.8, -0.5]), sun_intensity=1.2,
                 ambient=0.2)
WATER = WaterParams(beta_D=np.array([0.4, 0.1, 0.06]), beta_B=np.array([0.3, 0.08, 0.05]),
                    B_inf=np.array([0.03, 0.2, 0.25]))
GREY = np.array([150, 150, 150, 255], np.uint8)


def pinhole(width: int, height: int, hfov_deg: float) -> np.ndarray:
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def camera_view(K: np.ndarray, width: int, height: int, near: float = 0.1, far: float = 1000.0) -> View:
    """A view whose world frame is the camera frame (KITTI axes: x right, y down, z forward)."""
    return View(K=K, width=width, height=height, cam_from_world=np.eye(4), near=near, far=far)


def fronto_quad(K: np.ndarray, u: tuple[float, float], v: tuple[float, float], z: float) -> trimesh.Trimesh:
    """A flat rectangle at depth z (camera frame) whose image is exactly [u0, u1] x [v0, v1] (pixels)."""
    x = (np.array(u) - K[0, 2]) * z / K[0, 0]
    y = (np.array(v) - K[1, 2]) * z / K[1, 1]
    vertices = np.array([[x[0], y[0], z], [x[1], y[0], z], [x[1], y[1], z], [x[0], y[1], z]])
    return trimesh.Trimesh(vertices, [[0, 2, 1], [0, 3, 2]], vertex_colors=np.tile(GREY, (4, 1)), process=False)


def placed(key: str, mesh: trimesh.Trimesh, instance_id: int, role: str = "target",
           pose: np.ndarray | None = None) -> Placed:
    return Placed(
        instance_id=instance_id,
        role=role,
        class_name="Urchin" if role == "target" else None,
        asset=Asset(key=key, mesh=mesh, sha256=None, source="test"),
        variant=None,
        scale=1.0,
        world_from_obj=np.eye(4) if pose is None else pose,
        albedo_scale=np.ones(3, np.float32),
        albedo_bias=np.zeros(3, np.float32),
        footprint_m=0.0,
    )


def item_of(p: Placed) -> DrawItem:
    return DrawItem(mesh=to_render_mesh(p.asset.key, p.asset.mesh), world_from_obj=p.world_from_obj,
                    albedo_scale=p.albedo_scale, albedo_bias=p.albedo_bias, instance_id=p.instance_id)


def scene_of(objects: list[Placed]) -> Scene:
    """A scene holding `objects`, seen from the world origin (the labels read only its objects)."""
    return Scene(
        terrain=procedural_terrain("sand", 0, 12.0, 2, 0.0),
        terrain_albedo_scale=np.ones(3, np.float32),
        terrain_albedo_bias=np.zeros(3, np.float32),
        objects=tuple(objects),
        world_from_cam=np.eye(4),
        look_at=np.array([0.0, 0.0, 1.0]),
        look_at_instance=None,
        camera_tries=1,
        lighting=LIGHT,
        water=WATER,
        water_type=None,
        dropped=0,
    )


def label_frame(session, view: View, objects: list[Placed], extra: list[DrawItem] = (), water=WATER):
    """Render `objects` (plus unlabelled `extra` items) and label them as the pipeline does."""
    items = [*extra, *(item_of(p) for p in objects)]
    result = session.renderer.render(view, items, LIGHT, water, PRESETS["default"],
                                     Passes(clean=True, ids=True, range=True))
    return result, items, session.labels(view, scene_of(objects), items, result)


def box3d_of(obj: labels.KittiObject) -> labels.Box3D:
    return labels.Box3D(*obj.dims, *obj.location, obj.rotation_y)


def assert_encloses(obj: labels.KittiObject, K: np.ndarray) -> None:
    """The projected corners of the label's 3D box enclose its 2D box (pixel centres, 1e-3 px slack)."""
    uv = labels.project(box3d_of(obj).corners(), K)
    left, top, right, bottom = obj.box2d
    assert uv[:, 0].min() <= left + 1e-3 and uv[:, 0].max() >= right - 1e-3, (uv, obj.box2d)
    assert uv[:, 1].min() <= top + 1e-3 and uv[:, 1].max() >= bottom - 1e-3, (uv, obj.box2d)


def assert_finite(result) -> None:
    for name in ("image", "clean", "range_m"):
        a = getattr(result, name)
        assert not np.any(np.isnan(a)), name
    assert np.all(np.isfinite(result.image)) and np.all(np.isfinite(result.clean))


# --- borders ----------------------------------------------------------------------------------------------------

W, H = 16, 12
K = pinhole(W, H, 60.0)


@pytest.mark.parametrize("corner", ["top-left", "top-right", "bottom-left", "bottom-right"])
def test_object_cut_by_the_border_has_a_tight_box_at_the_edge_and_analytic_truncation(render_session, corner):
    # 8 x 8 px rectangle, half of it outside horizontally and a quarter of it vertically; edges on pixel boundaries.
    left_side, top_side = corner.endswith("left"), corner.startswith("top")
    u = (-4.5, 3.5) if left_side else (W - 4.5, W + 3.5)
    v = (-2.5, 5.5) if top_side else (H - 6.5, H + 1.5)
    target = placed(f"test/hard/border/{corner}", fronto_quad(K, u, v, 4.0), 1)
    view = camera_view(K, W, H)
    _, _, fl = label_frame(render_session, view, [target])
    [obj] = fl.objects
    expected_box = (0 if left_side else W - 4, 0 if top_side else H - 6, 3 if left_side else W - 1,
                    5 if top_side else H - 1)
    assert obj.box2d == expected_box
    assert fl.visible == fl.alone == {1: 24}
    # 1 - (inside fraction along u) * (along v) = 1 - (4 / 8) * (6 / 8)
    points = np.asarray(target.asset.mesh.vertices)
    assert obj.truncated == pytest.approx(0.625, abs=1e-9)
    assert obj.truncated == labels.truncation(points, K, W, H, view.near)
    assert obj.occluded == 0
    assert_encloses(obj, K)


# --- hidden and one-pixel targets -------------------------------------------------------------------------------


@pytest.mark.parametrize("wall_id", [0, 2], ids=["terrain-wall", "distractor-wall"])
def test_a_target_hidden_behind_a_wall_gets_no_label_line(render_session, wall_id):
    view = camera_view(K, W, H)
    target = placed("test/hard/hidden/target", fronto_quad(K, (5.5, 9.5), (3.5, 7.5), 10.0), 1)

    def frame(wall_z: float):
        quad = fronto_quad(K, (2.5, 12.5), (1.5, 9.5), wall_z)
        if wall_id:
            wall = placed(f"test/hard/wall/{wall_z}", quad, 2, "distractor")
            return label_frame(render_session, view, [target, wall])
        terrain = DrawItem(to_render_mesh(f"test/hard/terrain-wall/{wall_z}", quad), np.eye(4), np.ones(3, np.float32),
                           np.zeros(3, np.float32), 0)
        return label_frame(render_session, view, [target], [terrain])

    result, _, fl = frame(5.0)
    assert render_session.renderer.pixels_alone(view, item_of(target)) == 16
    assert not np.any(result.instance == 1)
    assert fl.objects == [] and fl.line_of == {} and fl.visible == {}
    assert kitti.format_label_file(fl.objects) == ""
    # The same wall behind the target: now it is seen whole.
    result, _, fl = frame(20.0)
    [obj] = fl.objects
    assert obj.box2d == (6, 4, 9, 7) and fl.visible == {1: 16} and obj.occluded == 0 and obj.truncated == 0


def test_a_far_target_covering_one_pixel_centre_gets_a_1x1_box(render_session):
    # A 20 cm cube 100 m away spans 0.03 px, centred on the ray through pixel (5, 4).
    view = camera_view(K, W, H)
    centre = 100.0 * np.linalg.solve(K, [5.0, 4.0, 1.0])
    cube = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    cube.visual.vertex_colors = GREY
    pose = np.eye(4)
    pose[:3, 3] = centre
    result, _, fl = label_frame(render_session, view, [placed("test/hard/one-pixel", cube, 1, pose=pose)])
    np.testing.assert_array_equal(np.argwhere(result.instance == 1), [[4, 5]])
    [obj] = fl.objects
    assert obj.box2d == (5, 4, 5, 4)
    left, top, right, bottom = kitti.parse_label_file(kitti.format_label_file(fl.objects))[0]["bbox"]
    assert left == right == 5 and top == bottom == 4
    assert fl.visible == fl.alone == {1: 1} and obj.occluded == 0 and obj.truncated == 0
    np.testing.assert_allclose(obj.dims, (0.2, 0.2, 0.2), rtol=1e-6)
    np.testing.assert_allclose(obj.location, centre + [0.0, 0.1, 0.0], rtol=1e-9, atol=1e-9)
    assert_encloses(obj, K)


# --- sampled scenes ---------------------------------------------------------------------------------------------


def check_sampled_frame(session, spec, index: int) -> tuple[labels.FrameLabels, int, int]:
    """Frame `index` of `spec` as the frame function samples and labels it, checked: each target with a visible pixel
    has one line, whose 2D box is the tight box of its instance pixels and whose 3D box is the yaw-only box of its
    vertices, enclosing the 2D box where it lies past the near plane. Returns (labels, labelled, enclosed)."""
    scene = session.scene(spec, index)
    view = session.view(spec, scene)
    items = session.draw_items(scene)
    result = session.renderer.render(view, items, scene.lighting, scene.water, PRESETS[spec.quality],
                                     Passes(ids=True))
    fl = session.labels(view, scene, items, result)
    boxes = labels.tight_boxes(result.instance)
    targets = [p.instance_id for p in scene.objects if p.role == "target"]
    expected_ids = [i for i in targets if i in boxes]
    assert list(fl.line_of) == expected_ids and list(fl.line_of.values()) == list(range(len(expected_ids)))
    enclosed = 0
    for i in expected_ids:
        obj, box = fl.objects[fl.line_of[i]], boxes[i]
        assert obj.box2d == (box.left, box.top, box.right, box.bottom)
        assert fl.visible[i] == box.pixels <= fl.alone[i]
        placed_obj = next(p for p in scene.objects if p.instance_id == i)
        assert obj.type == placed_obj.class_name
        corners = box3d_of(obj).corners()
        # The 3D box is the yaw-only box of the object's vertices in the camera frame.
        T = view.cam_from_world @ placed_obj.world_from_obj
        pts = np.asarray(placed_obj.asset.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
        assert labels.box3d(pts) == box3d_of(obj)
        if corners[:, 2].min() > view.near:
            assert_encloses(obj, np.asarray(spec.camera.K()))
            enclosed += 1
    return fl, len(expected_ids), enclosed


def test_label_boxes_are_the_tight_boxes_of_the_instance_image(render_session):
    spec = load_spec(EXAMPLE, {"camera.width": 96, "camera.height": 72})
    labelled = enclosed = 0
    for index in range(4):
        fl, n, e = check_sampled_frame(render_session, spec, index)
        labelled, enclosed = labelled + n, enclosed + e
        if index == 0:
            files = render_session.frame_files(spec, index)
            assert files["label_2/000000.txt"].decode() == kitti.format_label_file(fl.objects)
    assert labelled >= 6 and enclosed == labelled


# --- degenerate meshes ------------------------------------------------------------------------------------------

N = 15  # a 15 x 15 view with a 90-degree field: f = 7.5 px, principal point (7, 7)
K_SQ = pinhole(N, N, 90.0)


def cube(scale: float = 1.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=[2.0 * scale] * 3)
    mesh.visual.vertex_colors = GREY
    return mesh


def with_zero_area_faces() -> trimesh.Trimesh:
    m = cube()
    v = np.asarray(m.vertices)
    vertices = np.vstack([v, (v[0] + v[1]) / 2])  # a midpoint makes a collinear (zero-area) triangle
    mid = len(v)
    faces = np.vstack([m.faces, [[0, 0, 1], [2, 2, 2], [0, mid, 1], [3, 5, 3]]])
    colours = np.tile(GREY, (len(vertices), 1))
    return trimesh.Trimesh(vertices, faces, vertex_colors=colours, process=False)


def flipped() -> trimesh.Trimesh:
    m = cube()
    m.invert()
    return m


# name: (mesh, half size a of the cube in metres, scale in the pose)
DEGENERATE = {
    "plain": (cube, 1.0, 1.0),
    "zero-area-faces": (with_zero_area_faces, 1.0, 1.0),
    "flipped-winding": (flipped, 1.0, 1.0),
    "huge-pose-1e3": (cube, 1e3, 1e3),
    "tiny-pose-1e-4": (cube, 1e-4, 1e-4),
    "huge-vertices-1e3": (lambda: cube(1e3), 1e3, 1.0),
    "tiny-vertices-1e-4": (lambda: cube(1e-4), 1e-4, 1.0),
}


def degenerate_frame(session, name: str):
    make, a, scale = DEGENERATE[name]
    # On the optical axis with its front face at z = 3a: the face's image is [4.5, 9.5]^2, pixels 5..9.
    pose = np.diag([scale, scale, scale, 1.0])
    pose[2, 3] = 4.0 * a
    view = camera_view(K_SQ, N, N, near=0.1 * a, far=100.0 * a)
    return (*label_frame(session, view, [placed(f"test/hard/degenerate/{name}", make(), 1, pose=pose)]), a)


@pytest.mark.parametrize("name", list(DEGENERATE))
def test_degenerate_meshes_render_and_label_exactly(render_session, name):
    result, _, fl, a = degenerate_frame(render_session, name)
    assert_finite(result)
    block = np.zeros((N, N), bool)
    block[5:10, 5:10] = True
    np.testing.assert_array_equal(result.instance, block.astype(np.uint32))
    u, v = np.meshgrid(np.arange(N, dtype=np.float64), np.arange(N, dtype=np.float64))
    norms = np.linalg.norm(np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K_SQ).T, axis=-1)
    np.testing.assert_allclose(result.range_m[block], 3 * a * norms[block], rtol=1e-5)
    assert np.all(result.range_m[~block] == np.inf)
    np.testing.assert_allclose(result.image[~block], np.broadcast_to(WATER.B_inf.astype(np.float32), (N * N - 25, 3)),
                               atol=1e-6, rtol=0)
    [obj] = fl.objects
    assert obj.box2d == (5, 5, 9, 9) and fl.visible == fl.alone == {1: 25}
    assert obj.truncated == 0 and obj.occluded == 0
    np.testing.assert_allclose(obj.dims, (2 * a, 2 * a, 2 * a), rtol=1e-6)
    np.testing.assert_allclose(obj.location, (0.0, a, 4 * a), rtol=1e-6, atol=1e-9 * a)
    assert_encloses(obj, K_SQ)
    text = kitti.format_label_file(fl.objects)
    assert "nan" not in text.lower() and "inf" not in text.lower()


@pytest.mark.parametrize("name", [n for n in DEGENERATE if n != "plain"])
def test_degenerate_meshes_look_like_the_plain_cube(render_session, name):
    """Zero-area faces cover nothing; winding and scale change no pixel (both sides are lit, light is directional)."""
    plain, _, _, _ = degenerate_frame(render_session, "plain")
    other, _, _, _ = degenerate_frame(render_session, name)
    np.testing.assert_array_equal(other.instance, plain.instance)
    np.testing.assert_allclose(other.clean, plain.clean, atol=1e-6, rtol=0)
