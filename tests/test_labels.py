"""Tests of seasynth.worker.frame.labels: tight boxes, truncation, occlusion, yaw-only 3D boxes and angles."""

import math

import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from seasynth.worker.frame.labels import (
    Box2D,
    Box3D,
    KittiObject,
    alpha,
    box3d,
    clip_near,
    kitti_object,
    occlusion_level,
    project,
    tight_box_arrays,
    tight_boxes,
    truncation,
    wrap_angle,
    yaw_matrix,
)

W, H = 640, 480
K = np.array([[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]])


# --- tight boxes -------------------------------------------------------------------------------------------


def brute_force_boxes(instance):
    boxes = {}
    for i in np.unique(instance):
        if i == 0:
            continue
        rows, cols = np.nonzero(instance == i)
        boxes[int(i)] = Box2D(int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max()), int(rows.size))
    return boxes


@settings(deadline=None, max_examples=200)
@given(
    hnp.arrays(
        dtype=st.sampled_from([np.uint8, np.int32, np.uint16, np.int64]),
        shape=hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=12),
        elements=st.integers(0, 6),
    )
)
def test_tight_boxes_match_brute_force(instance):
    assert tight_boxes(instance) == brute_force_boxes(instance)


def test_tight_boxes_of_ids_past_16_bits_match_brute_force():
    """Ids that do not fit the 16-bit radix sort take the wide sort, with the same boxes."""
    rng = np.random.default_rng(3)
    instance = rng.choice(np.array([0, 1, 65535, 65536, 2**31 - 1], np.int64), size=(9, 13))
    assert tight_boxes(instance) == brute_force_boxes(instance)
    assert set(tight_boxes(instance)) == {1, 65535, 65536, 2**31 - 1}


def test_objects_touching_every_border():
    instance = np.zeros((5, 7), np.int32)
    instance[0, :] = 1  # top row; the columns below overwrite its ends
    instance[:, 0] = 2  # left column
    instance[:, -1] = 3  # right column
    instance[-1, 2:5] = 4  # bottom row
    boxes = tight_boxes(instance)
    assert boxes == brute_force_boxes(instance)
    assert boxes[1] == Box2D(1, 0, 5, 0, 5)
    assert boxes[2] == Box2D(0, 0, 0, 4, 5)
    assert boxes[3] == Box2D(6, 0, 6, 4, 5)
    assert boxes[4] == Box2D(2, 4, 4, 4, 3)


def test_whole_image_object_spans_the_image():
    assert tight_boxes(np.full((4, 9), 7, np.uint8)) == {7: Box2D(0, 0, 8, 3, 36)}


def test_one_pixel_object():
    instance = np.zeros((6, 6), np.uint16)
    instance[3, 4] = 9
    assert tight_boxes(instance) == {9: Box2D(4, 3, 4, 3, 1)}


def test_absent_ids_and_background_are_not_reported():
    instance = np.array([[0, 5], [5, 0]], np.int32)
    assert set(tight_boxes(instance)) == {5}
    assert tight_boxes(np.zeros((3, 3), np.int32)) == {}
    ids, boxes, counts = tight_box_arrays(np.zeros((3, 3), np.int32))
    assert ids.shape == (0,) and boxes.shape == (0, 4) and counts.shape == (0,)


def test_tight_boxes_rejects_bad_images():
    with pytest.raises(ValueError, match="integer"):
        tight_boxes(np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match="H, W"):
        tight_boxes(np.zeros((3, 3, 1), np.int32))
    with pytest.raises(ValueError, match=">= 0"):
        tight_boxes(np.array([[0, -1]], np.int32))


# --- projection and truncation ----------------------------------------------------------------------------


def test_project_pinhole():
    points = np.array([[0.0, 0.0, 2.0], [1.0, -2.0, 4.0]])
    expected = np.array([[319.5, 239.5], [319.5 + 500 / 4, 239.5 - 510 * 2 / 4]])
    np.testing.assert_allclose(project(points, K), expected, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="z > 0"):
        project(np.array([[0.0, 0.0, 0.0]]), K)


def sphere(centre, radius=1.0):
    return trimesh.creation.icosphere(subdivisions=5, radius=radius).vertices + np.asarray(centre)


def test_fully_inside_is_exactly_zero():
    assert truncation(sphere([0.3, -0.2, 10.0]), K, W, H, 0.1) == 0.0


def test_fully_outside_is_exactly_one():
    assert truncation(sphere([100.0, 0.0, 10.0]), K, W, H, 0.1) == 1.0
    assert truncation(sphere([0.0, -50.0, 10.0]), K, W, H, 0.1) == 1.0


def test_wholly_behind_the_camera_is_one():
    assert truncation(sphere([0.0, 0.0, -10.0]), K, W, H, 0.1) == 1.0
    assert truncation(np.array([[0.0, 0.0, 0.05]]), K, W, H, 0.1) == 1.0  # nearer than z_near


def test_sphere_on_the_left_border_on_axis_is_half():
    # The icosphere is mirror-symmetric in x; with cx = -0.5 its centre is on the optical axis and projects
    # to u = -0.5, so its projected box is symmetric about the image's left edge: exactly half is outside.
    K_edge = K.copy()
    K_edge[0, 2] = -0.5
    assert truncation(sphere([0.0, 0.0, 10.0]), K_edge, W, H, 0.1) == pytest.approx(0.5, abs=1e-12)


def test_sphere_on_the_left_border_off_axis_matches_the_analytic_sphere():
    # Off the optical axis a sphere's image is not centred on its centre's projection; the extreme rays are
    # the tangents at angles atan2(x, z) +- asin(r / d) in the x-z plane, so truncation is not 0.5 here.
    z, radius = 10.0, 1.0
    x = (-0.5 - K[0, 2]) * z / K[0, 0]  # centre projects to u = -0.5
    theta, delta = math.atan2(x, z), math.asin(radius / math.hypot(x, z))
    u_lo, u_hi = (K[0, 0] * math.tan(theta + s * delta) + K[0, 2] for s in (-1, 1))
    expected = (-0.5 - u_lo) / (u_hi - u_lo)
    assert expected > 0.52  # a visibly different number from the on-axis 0.5
    assert truncation(sphere([x, 0.0, z], radius), K, W, H, 0.1) == pytest.approx(expected, abs=1e-3)


def test_box_straddling_the_camera_plane_is_cut_at_the_near_plane():
    x0, x1, y0, y1, z_near = -1.0, 2.0, -0.5, 0.5, 0.1
    corners = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (-1.0, 5.0)])
    # The hull cut at z = z_near is the box x0..x1, y0..y1, z_near..5, whose extreme rays pass z = z_near.
    u_lo, u_hi = K[0, 0] * np.array([x0, x1]) / z_near + K[0, 2]
    v_lo, v_hi = K[1, 1] * np.array([y0, y1]) / z_near + K[1, 2]
    inside = (min(u_hi, W - 0.5) - max(u_lo, -0.5)) / (u_hi - u_lo)
    inside *= (min(v_hi, H - 0.5) - max(v_lo, -0.5)) / (v_hi - v_lo)
    assert truncation(corners, K, W, H, z_near) == pytest.approx(1 - inside, abs=1e-12)


def reference_clip(points, z_near):
    """Every crossing of z = z_near by a segment between a point behind and a point in front."""
    front = points[:, 2] >= z_near
    a, b = points[~front][:, None, :], points[front][None, :, :]
    t = (z_near - a[..., 2]) / (b[..., 2] - a[..., 2])
    cut = (a + t[..., None] * (b - a)).reshape(-1, 3)
    return np.concatenate([points[front], cut])


coords = st.floats(-3.0, 3.0, allow_nan=False)


@settings(deadline=None, max_examples=150)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(2, 25), st.just(3)), elements=coords),
    st.booleans(),
)
def test_near_plane_clipping_matches_all_pairs(points, flat):
    if flat:
        points[:, 1] = 0.5  # coplanar clouds take qhull's joggled path
    z_near = 0.1
    clipped, reference = clip_near(points, z_near), reference_clip(points, z_near)
    assert np.all(clipped[:, 2] >= z_near - 1e-12)
    if len(reference) == 0:
        assert len(clipped) == 0 and truncation(points, K, W, H, z_near) == 1.0
        return
    uv, uv_ref = project(clipped, K), project(reference, K)
    scale = np.abs(uv_ref).max() + 1.0
    np.testing.assert_allclose(uv.min(0), uv_ref.min(0), rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(uv.max(0), uv_ref.max(0), rtol=0, atol=1e-9 * scale)
    value = truncation(points, K, W, H, z_near)
    assert 0.0 <= value <= 1.0


def test_truncation_of_degenerate_boxes():
    point_inside = np.array([[0.0, 0.0, 5.0]])
    point_outside = np.array([[50.0, 0.0, 5.0]])
    assert truncation(point_inside, K, W, H, 0.1) == 0.0
    assert truncation(point_outside, K, W, H, 0.1) == 1.0
    # A horizontal segment from u = 319.5 to u = 819.5: 320 of its 500 px are inside (up to u = 639.5).
    segment = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]])
    assert truncation(segment, K, W, H, 0.1) == pytest.approx(1 - 320 / 500, abs=1e-12)


def test_truncation_rejects_bad_input():
    with pytest.raises(ValueError):
        truncation(np.zeros((0, 3)), K, W, H, 0.1)
    with pytest.raises(ValueError):
        truncation(np.array([[np.nan, 0.0, 1.0]]), K, W, H, 0.1)
    with pytest.raises(ValueError):
        truncation(np.array([[0.0, 0.0, 1.0]]), K, W, H, 0.0)


# --- occlusion -------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("visible", "alone", "level"),
    [(100, 100, 0), (90, 100, 0), (89, 100, 1), (50, 100, 1), (49, 100, 2), (0, 100, 2), (0, 0, 2), (12, 10, 0)],
)
def test_occlusion_levels(visible, alone, level):
    assert occlusion_level(visible, alone) == level


def test_occlusion_rejects_negative_counts():
    with pytest.raises(ValueError):
        occlusion_level(-1, 10)


# --- 3D boxes --------------------------------------------------------------------------------------------


def box_frame(points, box):
    """points (n, 3) in the box's own frame: x along l, y down from the bottom face, z along w."""
    return (points - np.array([box.x, box.y, box.z])) @ yaw_matrix(box.rotation_y)


def assert_encloses(box, points, tol=1e-9):
    local = box_frame(points, box)
    assert np.all(np.abs(local[:, 0]) <= box.l / 2 + tol)
    assert np.all(np.abs(local[:, 2]) <= box.w / 2 + tol)
    assert np.all(local[:, 1] <= tol) and np.all(local[:, 1] >= -box.h - tol)


def footprint_area(points, angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.ptp(points[:, 0] * c - points[:, 2] * s) * np.ptp(points[:, 0] * s + points[:, 2] * c)


@pytest.mark.parametrize("yaw", [0.0, 0.3, -1.2, np.pi / 2, -np.pi / 2, 2.9, -3.0, np.pi, 1.5707963])
def test_rotated_box_is_recovered(yaw):
    h, w, length, bottom_centre = 0.7, 1.3, 2.9, np.array([1.5, 0.8, 12.0])
    # A box mesh with its length along x, rotated by yaw about Y and moved so its bottom centre lands.
    mesh = trimesh.creation.box(extents=(length, h, w))
    points = (mesh.vertices + [0.0, -h / 2, 0.0]) @ yaw_matrix(yaw).T + bottom_centre
    box = box3d(points)
    # Exact (to rounding): sizes, bottom centre, and rotation_y modulo pi (a box is unchanged by a half turn).
    assert (box.h, box.w, box.l) == pytest.approx((h, w, length), abs=1e-9)
    assert (box.x, box.y, box.z) == pytest.approx(tuple(bottom_centre), abs=1e-9)
    half_turns = (box.rotation_y - yaw) / np.pi
    assert half_turns == pytest.approx(round(half_turns), abs=1e-9)
    assert -np.pi / 2 <= box.rotation_y < np.pi / 2
    gaps = np.linalg.norm(box.corners()[:, None, :] - points[None, :, :], axis=2)
    assert gaps.min(axis=1).max() < 1e-9 and gaps.min(axis=0).max() < 1e-9  # same 8 corners


def test_length_axis_points_along_camera_x_at_zero_yaw():
    box = Box3D(h=1.0, w=1.0, l=4.0, x=0.0, y=0.0, z=10.0, rotation_y=0.3)
    corners = box.corners()
    along = corners[0] - corners[3]  # +l/2 minus -l/2 at the same y and z offsets
    np.testing.assert_allclose(along, 4.0 * np.array([np.cos(0.3), 0.0, -np.sin(0.3)]), atol=1e-12)
    np.testing.assert_allclose(corners[:4, 1], 0.0)
    np.testing.assert_allclose(corners[4:, 1], -1.0)


clouds = hnp.arrays(
    np.float64,
    st.tuples(st.integers(1, 30), st.just(3)),
    elements=st.one_of(st.floats(-10.0, 10.0, allow_nan=False), st.sampled_from([0.0, 1.0, -2.5])),
)


_TINY = np.zeros((12, 3))
_TINY[0, 2] = _TINY[-1, 0] = 1.26453347e-237  # squared edges underflow to 0 unless scaled first


@settings(deadline=None, max_examples=200)
@given(clouds)
@example(_TINY)
def test_box3d_encloses_every_point_and_is_minimal(points):
    box = box3d(points)
    values = (box.h, box.w, box.l, box.x, box.y, box.z, box.rotation_y)
    assert np.all(np.isfinite(values))
    assert box.l >= box.w >= 0.0 and box.h >= 0.0
    assert -np.pi <= box.rotation_y < np.pi
    scale = 1.0 + np.abs(points).max()
    assert_encloses(box, points, tol=1e-9 * scale)
    area = box.l * box.w
    angles = np.r_[0.0, np.random.default_rng(0).uniform(-np.pi, np.pi, 100)]
    tol = 1e-9 * scale**2
    assert all(area <= footprint_area(points, a) + tol for a in angles)


@settings(deadline=None, max_examples=100)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(1, 30), st.just(3)), elements=st.floats(-1.0, 1.0)),
    st.floats(-np.pi, np.pi),
)
def test_projected_corners_enclose_projected_points(points, yaw):
    points = points @ yaw_matrix(yaw).T + [0.5, 0.2, 6.0]
    box = box3d(points)
    corners = box.corners()
    assert corners[:, 2].min() > 0  # the box is in front of the camera, so its projection is bounded
    uv, uv_corners = project(points, K), project(corners, K)
    assert np.all(uv_corners.min(0) <= uv.min(0) + 1e-9)
    assert np.all(uv_corners.max(0) >= uv.max(0) - 1e-9)


def test_degenerate_footprints():
    single = box3d(np.array([[1.0, 2.0, 3.0]]))
    assert single == Box3D(h=0.0, w=0.0, l=0.0, x=1.0, y=2.0, z=3.0, rotation_y=0.0)

    # Points on a line at 30 degrees from +x towards +z: length axis (cos, 0, -sin) gives ry = -30 degrees.
    t = np.linspace(0.0, 2.0, 5)
    direction = np.array([np.cos(np.pi / 6), 0.0, np.sin(np.pi / 6)])
    line = t[:, None] * direction + [0.0, 0.0, 5.0]
    line[:, 1] = [0.0, 0.5, 0.1, 0.2, 0.3]
    box = box3d(line)
    assert (box.l, box.w, box.h) == pytest.approx((2.0, 0.0, 0.5), abs=1e-12)
    assert box.rotation_y == pytest.approx(-np.pi / 6, abs=1e-12)
    assert (box.x, box.y, box.z) == pytest.approx(tuple(direction + [0.0, 0.5, 5.0]), abs=1e-12)

    flat = box3d(np.array([[0.0, 1.0, 4.0], [2.0, 1.0, 4.0], [2.0, 1.0, 5.0], [0.0, 1.0, 5.0]]))
    assert (flat.h, flat.w, flat.l, flat.y) == pytest.approx((0.0, 1.0, 2.0, 1.0), abs=1e-12)

    with pytest.raises(ValueError):
        box3d(np.zeros((0, 3)))


# --- angles ----------------------------------------------------------------------------------------------


def test_wrap_angle_edges():
    assert wrap_angle(np.pi) == -np.pi
    assert wrap_angle(-np.pi) == -np.pi
    assert wrap_angle(3 * np.pi) == pytest.approx(-np.pi)
    assert wrap_angle(0.0) == 0.0
    np.testing.assert_allclose(wrap_angle(np.array([0.5, 7.0, -7.0])), [0.5, 7.0 - 2 * np.pi, -7.0 + 2 * np.pi])


@given(st.floats(-1e4, 1e4, allow_nan=False))
def test_wrap_angle_range_and_equivalence(angle):
    wrapped = wrap_angle(angle)
    assert -np.pi <= wrapped < np.pi
    turns = (angle - wrapped) / (2 * np.pi)
    assert turns == pytest.approx(round(turns), abs=1e-9)


def test_alpha_is_yaw_minus_viewing_angle():
    ahead = Box3D(h=1.0, w=1.0, l=2.0, x=0.0, y=0.0, z=5.0, rotation_y=0.4)
    assert alpha(ahead) == pytest.approx(0.4, abs=1e-15)
    diagonal = Box3D(h=1.0, w=1.0, l=2.0, x=5.0, y=0.0, z=5.0, rotation_y=0.4)
    assert alpha(diagonal) == pytest.approx(0.4 - np.pi / 4, abs=1e-15)
    wraps = Box3D(h=1.0, w=1.0, l=2.0, x=-5.0, y=0.0, z=-5.0, rotation_y=1.4)
    assert alpha(wraps) == pytest.approx(1.4 + 3 * np.pi / 4 - 2 * np.pi, abs=1e-12)


# --- label records ---------------------------------------------------------------------------------------


def test_kitti_object_from_boxes():
    box = Box3D(h=1.0, w=2.0, l=3.0, x=1.0, y=0.5, z=8.0, rotation_y=0.2)
    obj = kitti_object("Urchin", Box2D(3, 4, 30, 40, 900), box, truncated=0.1, occluded=1)
    assert obj == KittiObject(
        "Urchin", 0.1, 1, alpha(box), (3.0, 4.0, 30.0, 40.0), (1.0, 2.0, 3.0), (1.0, 0.5, 8.0), 0.2
    )


@pytest.mark.parametrize("name", ["sea urchin", "", "Urchin\t", "a\nb"])
def test_class_names_with_whitespace_are_rejected(name):
    with pytest.raises(ValueError, match="class name") as error:
        KittiObject(name, 0.0, 0, 0.0, (0, 0, 1, 1), (1, 1, 1), (0, 0, 5), 0.0)
    assert repr(name) in str(error.value)


def test_kitti_object_validates_numbers():
    with pytest.raises(ValueError, match="occluded"):
        KittiObject("Urchin", 0.0, 4, 0.0, (0, 0, 1, 1), (1, 1, 1), (0, 0, 5), 0.0)
    with pytest.raises(ValueError, match="box2d"):
        KittiObject("Urchin", 0.0, 0, 0.0, (0, 0, 1), (1, 1, 1), (0, 0, 5), 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        KittiObject("Urchin", float("nan"), 0, 0.0, (0, 0, 1, 1), (1, 1, 1), (0, 0, 5), 0.0)
