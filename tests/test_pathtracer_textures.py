"""Textured scenes in the path tracer: the world's stored references are of the scenes the bench exports today, a
bundle of scenes unpacks to the same arrays, procedural images travel as names and digests, and a textured user
mesh (the markers example's glTF) shows the same pattern path traced as rendered."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

if importlib.util.find_spec("mitsuba") is None:  # only a missing Mitsuba skips
    pytest.skip("mitsuba is not installed (pip install -e '.[bench]')", allow_module_level=True)

from seasynth.bench import fidelity
from seasynth.bench.reference import REF_SUFFIX, load_reference, load_scene, same_scene
from seasynth.bench.reference_bundle import pack, unpack

ROOT = Path(__file__).resolve().parents[1]
STORED = ROOT / "bench" / "results" / "cpu" / "fidelity-references"


@pytest.fixture(scope="module")
def world_scenes(tmp_path_factory):
    out = tmp_path_factory.mktemp("world")
    return fidelity.export_scenes(out, configs=fidelity.WORLD_CONFIGS, platform="egl")


def test_the_worlds_stored_references_are_of_the_scenes_the_bench_exports_today(world_scenes):
    for name, path in zip(fidelity.WORLD_CONFIGS, world_scenes):
        pts = load_scene(path)
        if name in fidelity.REFERENCES_PENDING:  # none stored yet: once one is, it leaves the pending set
            assert not (STORED / f"{name}{REF_SUFFIX}").exists(), name
            continue
        ref = load_reference(STORED / f"{name}{REF_SUFFIX}")
        assert same_scene(ref, pts), name
        assert ref.halves[0].dtype == np.float32 and ref.spp >= 3000
        assert any(m.material is not None for m in pts.meshes)  # textured: the world's configurations all are
    long = load_scene(world_scenes[list(fidelity.WORLD_CONFIGS).index("long-turbid-sun")])
    reach = max(float(np.abs(np.asarray(m.vertices)[:, :2]).max()) for m in long.meshes)
    assert reach > 50.0  # the long view's far field reaches far past the 12 m tile
    for name in ("coastal-sun-particles", "turbid-lamps-particles"):  # marine snow travels as spheres
        spheres = load_scene(world_scenes[list(fidelity.WORLD_CONFIGS).index(name)]).spheres
        assert spheres is not None and len(spheres.radii) > 1000
        assert np.all((spheres.radii >= 0.25e-3 * (1 - 1e-9)) & (spheres.radii <= 2.5e-3 * (1 + 1e-9)))


def test_procedural_images_travel_as_their_names_and_digests(world_scenes):
    with np.load(world_scenes[0]) as z:
        names = z.files
        big = [k for k in names if z[k].ndim == 3]  # images would be (h, w, 3)
    assert not big
    assert any(k.endswith("_mat_base_sha256") for k in names) and any(k.endswith("_mat_base_key") for k in names)


def test_a_bundle_unpacks_to_the_same_arrays_and_is_about_one_scenes_size(world_scenes, tmp_path):
    bundle = tmp_path / "world.bundle.npz"
    manifest = pack(world_scenes[0].parent, bundle)
    assert sorted(manifest) == sorted(fidelity.WORLD_CONFIGS)
    paths = unpack(bundle, tmp_path / "out")
    for path in paths:
        original = world_scenes[0].parent / path.name
        with np.load(original) as a, np.load(path) as b:
            assert sorted(a.files) == sorted(b.files)
            assert all(np.array_equal(a[k], b[k]) and a[k].dtype == b[k].dtype for k in a.files)
    assert bundle.stat().st_size < 1.5 * max(p.stat().st_size for p in world_scenes)


def test_a_textured_user_mesh_shows_the_same_pattern_path_traced(render_session):
    """The markers example's frame 6 (three glTF markers printed with a black and white code): on the markers'
    pixels the path tracer's image and the renderer's agree in pattern (correlation) and level."""
    from seasynth.bench.fidelity_scene import exported_scene
    from seasynth.bench.pathtracer import render, render_ids
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import PRESETS
    from seasynth.worker.render import Passes

    spec = load_spec(ROOT / "examples" / "markers.yaml", {"camera.width": 64, "camera.height": 48,
                                                          "water.jerlov": ["I"], "water.depth_m": [5.0, 5.0]})
    s = render_session
    scene = s.scene(spec, 6)
    view, items = s.view(spec, scene), s.draw_items(scene)
    image = s.renderer.render(view, items, scene.light, None, PRESETS["default"], Passes()).image
    pts = exported_scene(s, spec, scene)
    assert sum(m.material is not None and m.material.mapping == "uv" for m in pts.meshes) >= 1
    traced = render(pts, 128, seed=3)
    ids = render_ids(pts)
    marker_ids = {p.instance_id for p in scene.objects if p.role == "target"}
    on = np.isin(ids, list(marker_ids))
    # inside the markers (all four neighbours too): edge pixels mix with the seabed, differently filtered
    on[1:-1, 1:-1] &= on[:-2, 1:-1] & on[2:, 1:-1] & on[1:-1, :-2] & on[1:-1, 2:]
    on[[0, -1]] = False
    on[:, [0, -1]] = False
    assert on.sum() > 40
    a, b = image[on].mean(axis=-1), traced[on].mean(axis=-1)
    assert np.corrcoef(a, b)[0, 1] > 0.9  # 0.92 here: the code's black and white cells in the same places
    assert b.mean() == pytest.approx(a.mean(), rel=0.05)  # 1.9% apart here (128 samples a pixel)
