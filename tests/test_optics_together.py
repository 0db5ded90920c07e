"""Every optical effect at once, in any combination: the frame is reproducible byte for byte in another process,
meta records exactly the effects switched on, and every label box is the tight box of its instance's pixels in the
image as made (after the port's resampling, with particles in front)."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.frame import kitti, labels

# Each effect's spec, with the name it records in meta's "optics".
EFFECTS = {
    "particles": {"water": {"particles": {"enabled": True, "density_per_m3": [2000.0, 4000.0]}}},
    "forward_scatter": {"water": {"forward_scatter": True}},
    "geometry": {"camera": {"port": {"kind": "flat"}, "distortion": [-0.2, 0.05, 0.001, 0.0, 0.0]}},
    "depth_of_field": {"camera": {"aperture_f": 1.4, "focus_m": 2.0, "sensor_width_mm": 36.0}},
    "motion_blur": {"camera": {"exposure_s": 0.02, "velocity_m_s": [0.5, 1.0]}},
    "vignetting": {"camera": {"vignetting": 1.0}},
    "sensor": {"noise": {"full_well_e": 5000.0, "read_noise_e": 4.0, "auto_exposure": 0.4,
                         "white_balance": "gray_world"}},
}
BASE = {
    "frames": 2, "quality": "draft",
    "camera": {"width": 48, "height": 36, "hfov_deg": 70.0},
    "targets": {"class_name": "Urchin", "count": [2, 4], "assets": [{"procedural": "urchin", "variants": 2}]},
    "water": {"jerlov": ["1C", "3C"], "depth_m": [4.0, 8.0], "solved_column": False},  # optics, not the column's light
    "outputs": {"instance": True, "depth": True, "range": True, "meta": True},
}


def merged(names: list[str], seed: int) -> dict:
    spec = json.loads(json.dumps({**BASE, "seed": seed}))
    for name in names:
        for section, fields in EFFECTS[name].items():
            spec[section] = {**spec.get(section, {}), **fields}
    return spec


def frame_digest(spec: dict, index: int) -> dict[str, str]:
    """sha256 of every file of frame `index`, made in a fresh process."""
    code = (
        "import hashlib, json, sys\n"
        "from seasynth.service.spec.dataset import parse_spec\n"
        "from seasynth.worker.frame.function import RenderSession\n"
        "spec, index = json.loads(sys.argv[1]), int(sys.argv[2])\n"
        "with RenderSession() as s:\n"
        "    files = s.frame_files(parse_spec(spec), index)\n"
        "print(json.dumps({k: hashlib.sha256(v).hexdigest() for k, v in files.items()}))\n"
    )
    done = subprocess.run([sys.executable, "-c", code, json.dumps(spec), str(index)], capture_output=True, text=True,
                          check=True, timeout=300)
    return json.loads(done.stdout)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(names=st.lists(st.sampled_from(sorted(EFFECTS)), min_size=2, max_size=len(EFFECTS), unique=True),
       seed=st.integers(0, 2**31 - 1))
def test_effects_together_are_recorded_reproducible_and_keep_labels_tight(render_session, names, seed):
    spec = merged(names, seed)
    files = render_session.frame_files(parse_spec(spec), 1)
    meta = json.loads(files["meta/000001.json"])
    assert set(meta["optics"]) == set(names)
    instance = np.asarray(Image.open(io.BytesIO(files["instance/000001.png"])))
    boxes = labels.tight_boxes(instance)
    lines = kitti.parse_label_file(files["label_2/000001.txt"].decode())
    for obj in meta["objects"]:
        if obj["label_line"] is not None:
            box = boxes[obj["instance_id"]]
            assert tuple(lines[obj["label_line"]]["bbox"]) == (box.left, box.top, box.right, box.bottom)
            assert obj["visible_pixels"] == box.pixels
    assert frame_digest(spec, 1) == {k: hashlib.sha256(v).hexdigest() for k, v in files.items()}
