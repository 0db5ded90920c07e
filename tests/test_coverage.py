"""Pixels alone counted on the GPU (seasynth.worker.render.coverage): for every object, the count equals the pixels its own
id pass marks, whatever its triangles' overlap, its region or the other objects in the batch."""

import numpy as np
import trimesh
from test_hard_cases import GREY, camera_view, fronto_quad, pinhole

from seasynth.worker.frame.function import to_render_mesh
from seasynth.worker.render import DrawItem
from seasynth.worker.render.coverage import clipped

W, H = 40, 30
K = pinhole(W, H, 70.0)
VIEW = camera_view(K, W, H, near=0.1, far=50.0)


def item(key: str, mesh: trimesh.Trimesh, instance_id: int, pose: np.ndarray | None = None) -> DrawItem:
    return DrawItem(mesh=to_render_mesh(key, mesh), world_from_obj=np.eye(4) if pose is None else pose,
                    albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32), instance_id=instance_id)


def spiky_balls(n: int) -> list[DrawItem]:
    """Icospheres with every vertex pushed out at random: many triangles overlap at each pixel, front and back."""
    rng = np.random.default_rng(11)
    items = []
    for k in range(n):
        ball = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
        ball.vertices *= rng.uniform(0.6, 1.6, (len(ball.vertices), 1))
        ball.visual.vertex_colors = np.tile(GREY, (len(ball.vertices), 1))
        pose = np.eye(4)
        pose[:3, 3] = [rng.uniform(-3.0, 3.0), rng.uniform(-2.0, 2.0), rng.uniform(3.0, 8.0)]
        items.append(item(f"test/coverage/ball{k}", ball, k + 1, pose))
    return items


def lone_ids(renderer, it: DrawItem) -> np.ndarray:
    return renderer.geometry(VIEW, [it])[0]


def test_counts_of_a_batch_equal_each_objects_own_id_pass(renderer):
    items = spiky_balls(12)
    counts = renderer.pixels_alone_many(VIEW, [(it, None) for it in items])
    expected = [int(np.count_nonzero(lone_ids(renderer, it))) for it in items]
    assert counts == expected
    assert sum(c > 0 for c in counts) >= 10  # most balls are in view: the comparison is not of zeros


def test_a_region_counts_only_the_pixels_inside_it_and_a_region_off_the_image_none(renderer):
    ball = spiky_balls(1)[0]
    ids = lone_ids(renderer, ball)
    rows, cols = np.nonzero(ids)
    left, top, right, bottom = cols.min(), rows.min(), cols.max(), rows.max()
    half = (int(left), int(top), int((left + right) // 2), int(bottom))
    inside = int(np.count_nonzero(ids[half[1]:half[3] + 1, half[0]:half[2] + 1]))
    assert 0 < inside < np.count_nonzero(ids)
    counts = renderer.pixels_alone_many(VIEW, [(ball, half), (ball, (W + 5, 0, W + 9, 4)), (ball, (-20, -20, W + 20, H + 20))])
    assert counts == [inside, 0, int(np.count_nonzero(ids))]
    assert renderer.pixels_alone(VIEW, ball, half) == inside


def test_two_overlapping_objects_each_count_as_if_alone(renderer):
    near = item("test/coverage/near", fronto_quad(K, (4.5, 24.5), (4.5, 19.5), 3.0), 1)
    far = item("test/coverage/far", fronto_quad(K, (9.5, 34.5), (9.5, 24.5), 6.0), 2)
    assert renderer.pixels_alone_many(VIEW, [(near, None), (far, None)]) == [20 * 15, 25 * 15]
    assert renderer.pixels_alone_many(VIEW, []) == []


def test_clipped_regions():
    assert clipped(None, 10, 8) == (0, 0, 9, 7)
    assert clipped((-3, 2, 4, 20), 10, 8) == (0, 2, 4, 7)
    assert clipped((10, 0, 12, 3), 10, 8) is None
    assert clipped((5, 5, 4, 6), 10, 8) is None
