"""The marine vocabulary through the generator: each kind drawn as targets (among the others as distractors) by the
frame function's own scene, draw items and labels, and each label's 2D box the tight box of its instance pixels."""

from __future__ import annotations

import pytest
from test_hard_cases import EXAMPLE, check_sampled_frame
from test_vocabulary import KINDS

from seasynth.service.spec.dataset import load_spec

FRAMES = 3


def kind_spec(kind: str):
    """examples/urchins.yaml at 96 x 72 with `kind` as the targets (class name the kind) and the rest as distractors."""
    others = [{"procedural": k, "variants": 3} for k in KINDS if k != kind]
    return load_spec(EXAMPLE, {"camera.width": 96, "camera.height": 72, "targets.class_name": kind,
                               "targets.assets": [{"procedural": kind, "variants": 6}], "targets.count": [2, 4],
                               "distractors.assets": others, "distractors.count": [2, 5]})


@pytest.mark.parametrize("kind", KINDS)
def test_each_box_is_the_tight_box_of_its_instance_pixels(render_session, kind):
    spec = kind_spec(kind)
    labelled = 0
    for index in range(FRAMES):
        _, n, _ = check_sampled_frame(render_session, spec, index)
        labelled += n
    assert labelled >= FRAMES * 2 - 2  # most targets are in view (the camera looks at one)
