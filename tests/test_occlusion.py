"""Occlusion through the renderer: targets partly hidden by distractors get KITTI's occluded level from the
visible fraction and a box that is the tight box of their visible pixels."""

import numpy as np
import pytest
from test_hard_cases import LIGHT, camera_view, fronto_quad, label_frame, pinhole, placed

from seasynth.worker.frame.function import PRESETS
from seasynth.worker.render import Passes, View
from seasynth.worker.scene.assets.procedural import procedural_asset
from seasynth.worker.scene.poses import look_at_pose, rigid_inverse

W, H = 24, 16
K = pinhole(W, H, 60.0)
# The target: a 10 x 5 px rectangle, columns 4..13 and rows 3..7 (above the image centre, so a region read
# upside down would miss it), 10 m away.
TARGET_U, TARGET_V = (3.5, 13.5), (2.5, 7.5)
TARGET_PX = 50


def pixels_of(session, view, items, instance_id: int) -> np.ndarray:
    """(h, w) bool: the pixels whose centre sees `instance_id` when `items` are drawn."""
    result = session.renderer.render(view, items, LIGHT, None, PRESETS["default"], Passes(ids=True))
    return result.instance == instance_id


def tight_box(mask: np.ndarray) -> tuple[float, float, float, float]:
    rows, cols = np.nonzero(mask)
    return float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max())


def expected_level(visible: int, alone: int) -> int:
    fraction = visible / alone
    return 0 if fraction >= 0.9 else 1 if fraction >= 0.5 else 2


# name: (occluding rectangles (u0, u1, v0, v1) at 5 m, visible pixels, occluded level, box (l, t, r, b))
CASES = {
    "one-column-hidden-is-0.9": ([(3.5, 4.5, 0.5, 9.5)], 45, 0, (5, 3, 13, 7)),
    "two-columns-hidden-0.8": ([(3.5, 5.5, 0.5, 9.5)], 40, 1, (6, 3, 13, 7)),
    "corner-hidden-0.7": ([(3.5, 8.5, 1.5, 5.5)], 35, 1, (4, 3, 13, 7)),
    "half-hidden-is-0.5": ([(8.5, 14.5, 0.5, 9.5)], 25, 1, (4, 3, 8, 7)),
    "middle-band-hidden-0.4": ([(5.5, 11.5, 0.5, 9.5)], 20, 2, (4, 3, 13, 7)),
    "two-occluders-0.3": ([(2.5, 8.5, 0.5, 9.5), (8.0, 15.0, 1.5, 4.5)], 15, 2, (9, 5, 13, 7)),
    "one-pixel-left-0.02": ([(3.5, 13.5, 2.5, 6.5), (3.5, 12.5, 6.5, 8.5)], 1, 2, (13, 7, 13, 7)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_target_behind_distractors_gets_its_level_and_the_tight_box_of_its_visible_pixels(render_session, case):
    rects, visible_px, level, box = CASES[case]
    view = camera_view(K, W, H)
    target = placed("test/occlusion/target", fronto_quad(K, TARGET_U, TARGET_V, 10.0), 1)
    walls = [placed(f"test/occlusion/wall/{r}", fronto_quad(K, r[:2], r[2:], 5.0), 2 + i, "distractor")
             for i, r in enumerate(rects)]
    result, items, fl = label_frame(render_session, view, [target, *walls])

    # Independently: the target's pixels drawn alone and among the walls.
    alone = pixels_of(render_session, view, [items[0]], 1)
    seen = result.instance == 1
    assert alone.sum() == TARGET_PX and seen.sum() == visible_px
    assert not np.any(seen & ~alone)
    assert expected_level(visible_px, TARGET_PX) == level
    assert tight_box(seen) == box

    [obj] = fl.objects  # distractors get no line
    assert fl.line_of == {1: 0} and fl.visible == {1: visible_px} and fl.alone == {1: TARGET_PX}
    assert obj.occluded == level
    assert obj.box2d == box
    assert obj.truncated == 0.0


def test_a_target_in_front_of_another_hides_it_and_stays_whole(render_session):
    view = camera_view(K, W, H)
    back = placed("test/occlusion/target", fronto_quad(K, TARGET_U, TARGET_V, 10.0), 1)
    front = placed("test/occlusion/front-target", fronto_quad(K, (7.5, 16.5), (4.5, 11.5), 6.0), 2)
    result, _, fl = label_frame(render_session, view, [back, front])
    # The front target covers columns 8..13 of rows 5..7 of the back one: 18 of its 50 pixels.
    assert np.count_nonzero(result.instance == 1) == 32 and np.count_nonzero(result.instance == 2) == 63
    assert fl.visible == {1: 32, 2: 63} and fl.alone == {1: 50, 2: 63}
    back_obj, front_obj = fl.objects
    assert (back_obj.occluded, front_obj.occluded) == (1, 0)
    assert back_obj.box2d == (4, 3, 13, 7) and front_obj.box2d == (8, 5, 16, 11)


# --- an urchin behind a rock, seen obliquely --------------------------------------------------------------------

OW, OH = 64, 48
OK = pinhole(OW, OH, 50.0)


def oblique_frame(session, offset_m: float):
    """An urchin at the origin and a rock `offset_m` to its side and 0.15 m nearer, seen from above and in front."""
    urchin, rock = procedural_asset("urchin", 1), procedural_asset("rock", 2)
    rock_pose = np.diag([1.6, 1.6, 1.6, 1.0])
    rock_pose[:3, 3] = [offset_m, -0.15, 0.0]
    eye, at = np.array([0.05, -0.5, 0.15]), np.array([0.0, 0.0, 0.06])
    view = View(K=OK, width=OW, height=OH, cam_from_world=rigid_inverse(look_at_pose(eye, at)), near=0.02, far=10.0)
    objects = [placed(urchin.key, urchin.mesh, 1), placed(rock.key, rock.mesh, 2, "distractor", pose=rock_pose)]
    return (view, *label_frame(session, view, objects))


def test_oblique_occlusion_levels_match_independent_pixel_counts(render_session):
    # The rock slides across in front of the urchin: whole (0), partly hidden (1, 2), nearly gone (2), whole again.
    seen_levels = set()
    for offset in np.linspace(-0.15, 0.15, 13):
        view, result, items, fl = oblique_frame(render_session, float(offset))
        alone = pixels_of(render_session, view, [items[0]], 1)
        seen = result.instance == 1
        if not seen.any():
            assert fl.objects == []
            continue
        [obj] = fl.objects
        assert fl.alone == {1: int(alone.sum())} and fl.visible == {1: int(seen.sum())}
        assert obj.occluded == expected_level(int(seen.sum()), int(alone.sum()))
        assert obj.box2d == tight_box(seen)
        seen_levels.add(obj.occluded)
    assert seen_levels == {0, 1, 2}
