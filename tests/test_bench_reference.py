"""Stored path-traced references: scenes round-trip through their files with their digest, and merging renders
weights each by its samples and refuses what cannot be merged."""

import dataclasses

import numpy as np
import pytest

from seasynth.bench.pathtracer import PTLamp, PTMesh, PTScene, PTSpheres
from seasynth.bench.reference import (
    Reference,
    load_reference,
    load_scene,
    merge,
    save_reference,
    save_scene,
    scene_digest,
)


def scene(**change) -> PTScene:
    rng = np.random.default_rng(0)
    mesh = PTMesh(rng.random((5, 3), dtype=np.float32), np.array([[0, 1, 2], [2, 3, 4]], np.uint32),
                  rng.random((5, 3), dtype=np.float32), 3)
    lamp = PTLamp(np.array([0.1, 0.2, -1.0]), np.array([0.0, 0.0, -1.0]), 40.0, 20.0, np.array([3.0, 2.0, 1.0]))
    fields = dict(meshes=(mesh, mesh), K=np.array([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]), width=16, height=12,
                  world_from_cam=np.eye(4), sigma_a=np.array([0.3, 0.05, 0.02]), sigma_s=np.array([0.3, 0.4, 0.5]),
                  g=0.92, surface_z=10.0, sun_dir_world=np.array([0.0, 0.0, 1.0]),
                  sun_irradiance_rgb=np.array([1.0, 1.0, 1.0]), sky_radiance_rgb=np.array([0.1, 0.2, 0.3]),
                  lamps=(lamp,))
    return PTScene(**{**fields, **change})


def test_a_scene_round_trips_through_its_file_with_its_digest(tmp_path):
    s = scene()
    save_scene(s, tmp_path / "a.scene.npz")
    back = load_scene(tmp_path / "a.scene.npz")
    assert scene_digest(back) == scene_digest(s)
    assert len(back.meshes) == 2 and back.meshes[1].instance_id == 3 and len(back.lamps) == 1
    assert back.lamps[0].cutoff_deg == 40.0 and back.width == 16 and back.g == 0.92
    assert scene_digest(scene(g=0.9)) != scene_digest(s)  # any change of the scene changes its digest
    assert scene_digest(scene(lamps=())) != scene_digest(s)


def test_a_scene_with_spheres_round_trips_and_one_without_has_no_sphere_arrays(tmp_path):
    rng = np.random.default_rng(1)
    spheres = PTSpheres(rng.random((7, 3)), rng.uniform(1e-4, 3e-3, 7), rng.random((7, 3), dtype=np.float32))
    s = scene(spheres=spheres)
    save_scene(s, tmp_path / "s.scene.npz")
    back = load_scene(tmp_path / "s.scene.npz")
    assert scene_digest(back) == scene_digest(s) != scene_digest(scene())
    for name in ("radii", "albedo"):
        assert np.array_equal(getattr(back.spheres, name), getattr(spheres, name))
    # centres at the path tracer's precision: a last-bit change (one float64 ulp) leaves the scene, and its digest
    assert np.array_equal(back.spheres.centres, spheres.centres.astype(np.float32))
    nudged = dataclasses.replace(spheres, centres=np.nextafter(spheres.centres, 2.0))
    assert scene_digest(scene(spheres=nudged)) == scene_digest(s)
    save_scene(scene(), tmp_path / "n.scene.npz")
    with np.load(tmp_path / "n.scene.npz") as z:
        assert not [k for k in z.files if k.startswith("spheres")]  # scenes before spheres keep their digests
    assert load_scene(tmp_path / "n.scene.npz").spheres is None


def ref(value: float, spp: int, seeds, digest="x") -> Reference:
    h = np.full((2, 2, 3), value, np.float32)
    return Reference((h, h + 1), spp, "cuda_ad_rgb", 2.0, "gpu", digest, tuple(seeds))


def test_merging_weights_each_render_by_its_samples(tmp_path):
    m = merge(ref(1.0, 100, [0]), ref(4.0, 300, [1]))
    assert m.spp == 400 and m.seed_bases == (0, 1) and m.seconds == 4.0
    np.testing.assert_allclose(m.halves[0], 3.25)
    np.testing.assert_allclose(m.halves[1], 4.25)
    save_reference(m, tmp_path / "m.ref.npz")
    back = load_reference(tmp_path / "m.ref.npz")
    assert back.seed_bases == (0, 1) and back.spp == 400 and back.scene_sha256 == "x"
    np.testing.assert_array_equal(back.mean, m.mean)


def test_merging_refuses_reused_seeds_and_other_scenes():
    with pytest.raises(ValueError, match="seed bases"):
        merge(ref(1.0, 10, [0, 2]), ref(1.0, 10, [2]))
    with pytest.raises(ValueError, match="different scenes"):
        merge(ref(1.0, 10, [0]), ref(1.0, 10, [1], digest="y"))
    import dataclasses

    housed = dataclasses.replace(ref(1.0, 10, [1]), lamp_housing_m=0.02)
    with pytest.raises(ValueError, match="lamp housings differ"):
        merge(ref(1.0, 10, [0]), housed)
    both = merge(dataclasses.replace(ref(1.0, 10, [0]), lamp_housing_m=0.02), housed)
    assert both.lamp_housing_m == 0.02


def test_the_stored_fidelity_references_are_of_the_scenes_the_bench_exports_today(tmp_path):
    """Scene export drift (geometry, camera, water, lights) would silently orphan the committed references: each
    pinned configuration's exported scene must be its reference's (the digest, or on a machine whose float kernels
    round otherwise the fingerprint), and a mismatched one is refused."""
    from pathlib import Path

    from seasynth.bench import fidelity
    from seasynth.bench.reference import REF_SUFFIX, SCENE_SUFFIX, same_scene

    stored = Path(__file__).resolve().parents[1] / "bench" / "results" / "cpu" / "fidelity-references"
    paths = fidelity.export_scenes(tmp_path, configs=fidelity.CONFIGS, platform="egl")
    assert [p.name for p in paths] == [f"{n}{SCENE_SUFFIX}" for n in fidelity.CONFIGS]
    for name, path in zip(fidelity.CONFIGS, paths):
        pts = load_scene(path)
        assert same_scene(load_reference(stored / f"{name}{REF_SUFFIX}"), pts), name
        assert fidelity.stored_reference(stored, name, pts).spp > 10_000
    with pytest.raises(SystemExit, match="rendered for another scene"):
        fidelity.stored_reference(stored, "ocean-sun", load_scene(paths[0]))  # clear-ocean-sun's scene
    assert fidelity.stored_reference(tmp_path, "ocean-sun", load_scene(paths[0])) is None  # none stored there


def test_the_path_tracers_cost_is_a_fixed_part_and_a_part_per_sample():
    from seasynth.bench.fidelity import fit_cost

    cost = fit_cost(64, 2.4, 256, 7.5)
    assert cost.s_per_spp == pytest.approx(5.1 / 192)
    assert cost.fixed_s == pytest.approx(2.4 - 64 * 5.1 / 192)
    # 1,230 samples cost the fixed part once, not once per 64 samples as scaling the short render would count it
    assert cost.seconds(1230) == pytest.approx(cost.fixed_s + 1230 * cost.s_per_spp)
    assert cost.seconds(1230) < 2.4 * 1230 / 64 - 10
    # where the line's parts would not both be positive (a longer render timed no slower, or slower per sample than
    # the shorter: large frames render in several calls), the longer render's own rate and no fixed part, a line
    # through it and never above either timed render
    for low, high in ((2.4, 2.3), (1.0, 8.0), (24.81, 113.9)):
        c = fit_cost(64, low, 256, high)
        assert (c.fixed_s, c.s_per_spp) == pytest.approx((0.0, high / 256))
        assert c.seconds(256) == pytest.approx(high)
    with pytest.raises(ValueError, match="spp_high"):
        fit_cost(64, 1.0, 64, 2.0)


@pytest.mark.parametrize(("size", "names"), [((160, 120), None), ((640, 480), ("clear-lamps",))])
def test_the_stored_references_at_other_sizes_are_of_the_scenes_and_tables_committed(tmp_path, size, names):
    import json
    from pathlib import Path

    from seasynth.bench import fidelity
    from seasynth.service.spec.dataset import spec_digest

    results = Path(__file__).resolve().parents[1] / "bench" / "results" / "cpu"
    configs = {n: t for n, t in fidelity.CONFIGS.items() if names is None or n in names}
    paths = fidelity.export_scenes(tmp_path, configs=configs, platform="egl", size=size)
    table = json.loads((results / "fidelity-resolution" / f"{size[0]}x{size[1]}" / "fidelity.json").read_text())
    assert table["resolution"] == list(size) and table["configs"] == configs
    for (name, text), path in zip(configs.items(), paths):
        assert path.name == f"{name}-{size[0]}x{size[1]}.scene.npz"
        pts = load_scene(path)
        assert (pts.width, pts.height) == size
        ref = fidelity.stored_reference(results / "fidelity-references", name, pts)
        assert ref is not None and ref.spp > 10_000 and ref.halves[0].shape == (size[1], size[0], 3)
        assert table["references"][name]["scene_sha256"] == ref.scene_sha256
        assert {r["spec_sha256"] for r in table["rows"] if r["config"] == name} == {
            spec_digest(fidelity.config_spec(text, size))}
    for r in table["rows"]:  # the equal-error columns follow from the row's own cost line
        assert r["path_tracer_equal_error_s"] == pytest.approx(
            r["path_tracer_fixed_s"] + r["path_tracer_ms_per_spp"] / 1e3 * r["path_tracer_equal_error_spp"],
            rel=0.01, abs=0.1)
        # both columns are rounded (seconds to 0.1, the speedup to a whole number): together they differ by up to
        # 0.05 s plus half a frame's time
        assert r["speedup_equal_error"] * r["ms_per_frame"] / 1e3 == pytest.approx(
            r["path_tracer_equal_error_s"], rel=0.01, abs=0.05 + 0.5 * r["ms_per_frame"] / 1e3 + 1e-9)


def test_references_rendered_apart_merge_by_name_into_one_folder_even_in_place(tmp_path):
    from seasynth.bench.reference_merge import main, merge_folders

    for folder, value, spp, seed in (("stored", 1.0, 100, 0), ("gpu0", 4.0, 300, 1), ("gpu1", 2.0, 100, 2)):
        (tmp_path / folder).mkdir()
        save_reference(ref(value, spp, [seed]), tmp_path / folder / "turbid.ref.npz")
    save_reference(ref(7.0, 10, [5], digest="other"), tmp_path / "gpu1" / "clear.ref.npz")
    main([str(tmp_path / "stored"), *(str(tmp_path / f) for f in ("stored", "gpu0", "gpu1"))])
    back = load_reference(tmp_path / "stored" / "turbid.ref.npz")
    assert back.spp == 500 and back.seed_bases == (0, 1, 2) and back.seconds == 6.0
    np.testing.assert_allclose(back.halves[0], (100 * 1.0 + 300 * 4.0 + 100 * 2.0) / 500)
    assert load_reference(tmp_path / "stored" / "clear.ref.npz").spp == 10  # a name in one folder only is copied
    assert sorted(p.name for p in (tmp_path / "stored").iterdir()) == ["clear.ref.npz", "turbid.ref.npz"]
    # A render that reuses a seed base is refused naming its file, and nothing is written.
    save_reference(ref(9.0, 100, [1]), tmp_path / "gpu1" / "turbid.ref.npz")
    with pytest.raises(ValueError, match="gpu1/turbid.ref.npz: merge: both used seed bases"):
        merge_folders(tmp_path / "merged", [tmp_path / "gpu0", tmp_path / "gpu1"])
    assert not (tmp_path / "merged").exists()
    with pytest.raises(SystemExit, match="not a folder"):
        main([str(tmp_path / "x"), str(tmp_path / "missing")])
