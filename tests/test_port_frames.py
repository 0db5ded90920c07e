"""Frames through a port and a distorting lens (seasynth.worker.optics.geometry): range along each water ray against
a plane's analytic intersection, depth consistent with it, boxes tight on the resampled instance image, no change
with the effect off, and the same bytes from another process."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys

import numpy as np
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from spec_helpers import MAPPING

from seasynth.service.camera_model import CameraModel
from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.frame import kitti, labels
from seasynth.worker.frame.function import DEPTH_SCALE, PRESETS, depth_png16, to_render_mesh
from seasynth.worker.optics.base import Shot
from seasynth.worker.optics.geometry import Geometry
from seasynth.worker.render import DrawItem, Lighting, Passes, View

SETTINGS = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
PORTS = st.sampled_from([
    {"kind": "flat"},
    {"kind": "flat", "thickness_mm": 25.0, "glass_index": 1.77, "distance_mm": 5.0},
    {"kind": "dome", "pupil_offset_mm": [0.0, 0.0, 15.0]},
    {"kind": "dome", "pupil_offset_mm": [4.0, -3.0, -10.0], "glass_index": 1.52},
    {"kind": "none"},
])
DISTORTIONS = st.sampled_from([[0.0] * 5, [-0.2, 0.05, 0.0, 0.0, 0.0], [0.1, 0.0, 0.002, -0.003, 0.0]])


def plane_item(normal: np.ndarray, c: float, instance_id: int = 1) -> DrawItem:
    """A 400 m square on the plane normal . p = c (camera frame = world)."""
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    corners = c * normal + 200.0 * np.array([a + b, a - b, -a - b, -a + b])
    mesh = trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]], process=False)
    mesh.visual.vertex_colors = np.full((4, 4), 200, np.uint8)
    return DrawItem(mesh=to_render_mesh(f"plane{normal.tolist()}{c}", mesh), world_from_obj=np.eye(4),
                    albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32),
                    instance_id=instance_id)


@SETTINGS
@given(port=PORTS, distortion=DISTORTIONS, tilt=st.tuples(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4)),
       distance=st.floats(0.5, 20.0))
def test_range_is_the_distance_along_the_water_ray_to_a_plane_and_depth_its_z(renderer, port, distortion, tilt,
                                                                               distance):
    spec = parse_spec({"camera": {"width": 64, "height": 48, "hfov_deg": 80.0, "port": port,
                                  "distortion": distortion}})
    model = CameraModel.from_spec(spec.camera)
    normal = np.array([tilt[0], tilt[1], 1.0]) / np.linalg.norm([tilt[0], tilt[1], 1.0])
    item = plane_item(normal, distance)
    view = View(K=model.K, width=64, height=48, cam_from_world=np.eye(4), near=0.02, far=300.0)
    shot = Shot(spec=spec, index=0, scene=None, view=view, render_view=view, items=[item])
    effect = Geometry()
    if not effect.on(spec):
        return
    effect.prepare(shot)
    wide = renderer.render(shot.render_view, [item], Lighting(np.array([0.0, -1.0, 0.0]), 1.0, 0.3), None,
                           PRESETS["fast"], Passes(ids=True, range=True))
    out = effect.develop(shot, wide)
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    o, d = model.pixel_rays(u, v)
    t = (distance - o @ normal) / (d @ normal)  # the plane's analytic intersection along each water ray
    np.testing.assert_allclose(out.range_m, t, rtol=1e-4)  # measured: <= 4e-5 (float32 range, 1 m at 0.5 m)
    assert (out.instance == 1).all()
    z = o[..., 2] + t * d[..., 2]
    depth = depth_png16(out.range_m, shot.range_norms) / DEPTH_SCALE
    assert np.all(np.abs(depth - z) <= 0.5 / DEPTH_SCALE + 1e-4 * z)  # PNG rounding and the range's own error


@SETTINGS
@given(distance=st.floats(0.05, 0.6), tilt=st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2)),
       port_mm=st.floats(950.0, 1000.0))
def test_a_surface_inside_a_long_ports_housing_has_range_0_and_no_depth(renderer, distance, tilt, port_mm):
    """camera.port.distance_mm may be up to 1 m: a surface nearer than the window clamps to range 0 (it touches
    the port), and its depth is no measurement (0), not 0 / 0."""
    spec = parse_spec({"camera": {"width": 32, "height": 24, "hfov_deg": 60.0,
                                  "port": {"kind": "flat", "distance_mm": port_mm}}})
    normal = np.array([tilt[0], tilt[1], 1.0]) / np.linalg.norm([tilt[0], tilt[1], 1.0])
    item = plane_item(normal, distance)
    view = View(K=np.asarray(spec.camera.K()), width=32, height=24, cam_from_world=np.eye(4), near=0.02, far=300.0)
    shot = Shot(spec=spec, index=0, scene=None, view=view, render_view=view, items=[item])
    effect = Geometry()
    effect.prepare(shot)
    wide = renderer.render(shot.render_view, [item], Lighting(np.array([0.0, -1.0, 0.0]), 1.0, 0.3), None,
                           PRESETS["fast"], Passes(ids=True, range=True))
    out = effect.develop(shot, wide)
    assert np.all(out.range_m == 0.0) and np.all(np.isfinite(shot.range_norms))
    assert not depth_png16(out.range_m, shot.range_norms).any()


def port_spec(port: dict, distortion: list[float], seed: int) -> dict:
    return {**MAPPING, "seed": seed, "frames": 1, "targets": {**MAPPING["targets"], "count": [4, 8]},
            "camera": {**MAPPING["camera"], "width": 96, "height": 72, "port": port, "distortion": distortion},
            "outputs": {"labels": True, "instance": True, "meta": True, "depth": True}}


@SETTINGS
@given(port=PORTS, distortion=DISTORTIONS, seed=st.integers(0, 2**31))
def test_boxes_are_tight_on_the_resampled_instance_image_and_counts_agree(render_session, port, distortion, seed):
    spec = parse_spec(port_spec(port, distortion, seed))
    files = render_session.frame_files(spec, 0)
    instance = np.asarray(Image.open(io.BytesIO(files["instance/000000.png"])))
    lines = kitti.parse_label_file(files["label_2/000000.txt"].decode())
    meta = json.loads(files["meta/000000.json"])
    boxes = labels.tight_boxes(instance)
    seen = set()
    for obj in meta["objects"]:
        k = obj["label_line"]
        if k is None:  # every target seen has a line (a DontCare one below the filters)
            assert obj["instance_id"] not in boxes or obj["role"] != "target"
            continue
        box = boxes[obj["instance_id"]]
        seen.add(k)
        assert tuple(lines[k]["bbox"]) == (box.left, box.top, box.right, box.bottom)
        assert obj["visible_pixels"] == box.pixels <= obj["pixels_alone"]
    assert seen == set(range(len(lines)))
    assert ("model" in meta["camera"]) == (port["kind"] != "none" or any(distortion))
    if "model" in meta["camera"]:
        assert CameraModel.from_record(meta["camera"]["model"]).record() == meta["camera"]["model"]


def test_port_none_and_zero_distortion_change_no_byte(render_session):
    plain = {**MAPPING, "frames": 1, "outputs": {"labels": True, "instance": True, "meta": True, "depth": True}}
    said = {**plain, "camera": {**plain["camera"], "port": {"kind": "none", "thickness_mm": 3.0},
                                "distortion": [0.0, 0.0, 0.0, 0.0, 0.0]}}
    a, b = parse_spec(plain), parse_spec(said)
    assert not Geometry().on(b)
    assert render_session.frame_files(a, 0) == render_session.frame_files(b, 0)
    assert "optics" not in json.loads(render_session.frame_files(b, 0)["meta/000000.json"])


DIGEST = """
import hashlib, json, sys
from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.frame.function import RenderSession
with RenderSession() as s:
    files = s.frame_files(parse_spec(json.loads(sys.argv[1])), 0)
print(hashlib.sha256(b"".join(k.encode() + v for k, v in sorted(files.items()))).hexdigest())
"""


def test_port_frames_are_byte_identical_from_another_process(render_session):
    data = port_spec({"kind": "flat", "thickness_mm": 12.0}, [-0.1, 0.02, 0.001, 0.0, 0.0], 5)
    files = render_session.frame_files(parse_spec(data), 0)
    here = hashlib.sha256(b"".join(k.encode() + v for k, v in sorted(files.items()))).hexdigest()
    run = subprocess.run([sys.executable, "-c", DIGEST, json.dumps(data)], capture_output=True, text=True,
                         check=False)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == here


def sphere_item(centre, radius: float, instance_id: int) -> DrawItem:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius).apply_translation(centre)
    mesh.visual.vertex_colors = np.full((len(mesh.vertices), 4), 150, np.uint8)
    return DrawItem(mesh=to_render_mesh(f"sphere{list(centre)}{radius}", mesh), world_from_obj=np.eye(4),
                    albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32), instance_id=instance_id)


@SETTINGS
@given(port=PORTS, distortion=DISTORTIONS, x=st.floats(-0.8, 0.8), y=st.floats(-0.5, 0.5))
def test_objects_alone_are_counted_in_the_output_image_as_the_frame_samples_it(renderer, port, distortion, x, y):
    spec = parse_spec({"camera": {"width": 64, "height": 48, "hfov_deg": 80.0, "port": port,
                                  "distortion": distortion}})
    effect = Geometry()
    if not effect.on(spec):
        return
    target = sphere_item([x, y, 3.0], 0.4, 1)
    # on the sight line to the target (from the pupil), a little aside: it hides part of the target, never all
    occluder = sphere_item([x * 2.0 / 3.0 + 0.05, y * 2.0 / 3.0, 2.0], 0.15, 2)
    background = plane_item(np.array([0.0, 0.0, 1.0]), 8.0, instance_id=0)
    counts = []
    for items in ([background, target], [background, target, occluder]):
        view = View(K=CameraModel.from_spec(spec.camera).K, width=64, height=48, cam_from_world=np.eye(4), near=0.02,
                    far=300.0)
        shot = Shot(spec=spec, index=0, scene=None, view=view, render_view=view, items=items)
        effect = Geometry()
        effect.prepare(shot)
        wide = renderer.render(shot.render_view, items, Lighting(np.array([0.0, -1.0, 0.0]), 1.0, 0.3), None,
                               PRESETS["fast"], Passes(ids=True, range=True))
        out = effect.develop(shot, wide)
        mask = out.instance == 1
        counts.append((int(mask.sum()), effect.pixels_alone(shot, renderer, [target])[0], mask))
    (seen, alone, mask), (seen_behind, alone_behind, _) = counts
    assert seen == alone > 0  # nothing in front: every pixel it has alone it shows
    assert seen_behind < seen and alone_behind >= seen_behind  # the occluder hides some
    # its hidden pixels are sampled where the rays met the occluder: the count moves by pixels of its outline at most
    inner = mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    assert abs(alone_behind - alone) <= seen - int(inner.sum())
