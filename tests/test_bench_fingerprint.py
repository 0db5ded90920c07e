"""A scene's fingerprint: what ties a stored reference to its scene on machines whose float kernels round the
export's last bits otherwise (BLAS and SIMD paths follow the CPU). Last-bit changes of every float leave it; a change
of any one value past its stated tolerance, of a dtype, shape, face or image does not; stored references carry it."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.bench.pathtracer import PTLamp, PTMesh, PTScene
from seasynth.bench.reference import (
    FINGERPRINT_ATOL,
    FINGERPRINT_RTOL,
    REF_SUFFIX,
    Reference,
    _scene_arrays,
    fingerprints_agree,
    load_reference,
    merge,
    same_scene,
    save_reference,
    scene_digest,
    scene_fingerprint,
    stamp_fingerprint,
)

STORED = Path(__file__).resolve().parents[1] / "bench" / "results" / "cpu" / "fidelity-references"


def random_scene(seed: int, vertices: int) -> PTScene:
    rng = np.random.default_rng(seed)
    meshes = tuple(PTMesh(rng.normal(0.0, 5.0, (vertices, 3)).astype(np.float32),
                          rng.integers(0, vertices, (max(vertices // 2, 1), 3)).astype(np.uint32),
                          rng.random((vertices, 3), dtype=np.float32), i + 1) for i in range(2))
    lamp = PTLamp(rng.normal(size=3), np.array([0.0, 0.0, -1.0]), 40.0, 20.0, rng.random(3) * 5)
    world = np.eye(4)
    world[:3, 3] = rng.normal(size=3)
    return PTScene(meshes=meshes, K=np.array([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]), width=16, height=12,
                   world_from_cam=world, sigma_a=rng.random(3), sigma_s=rng.random(3), g=0.92, surface_z=10.0,
                   sun_dir_world=np.array([0.0, 0.0, 1.0]), sun_irradiance_rgb=rng.random(3),
                   sky_radiance_rgb=rng.random(3) * 0.1, lamps=(lamp,))


def nudged(a: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """`a` moved by `steps` (signed, per element) steps of its own float type."""
    out = a.copy()
    for _ in range(int(np.abs(steps).max(initial=0))):
        move = np.abs(steps) > 0
        out[move] = np.nextafter(out[move], np.where(steps[move] > 0, np.inf, -np.inf).astype(a.dtype))
        steps = steps - np.sign(steps)
    return out


def nudge_scene(scene: PTScene, rng: np.random.Generator, most: int) -> PTScene:
    def n(a):
        a = np.asarray(a)
        return nudged(a, rng.integers(-most, most + 1, a.shape))
    meshes = tuple(dataclasses.replace(m, vertices=n(m.vertices), albedo=n(m.albedo)) for m in scene.meshes)
    lamps = tuple(dataclasses.replace(la, position_world=n(la.position_world), direction_world=n(la.direction_world))
                  for la in scene.lamps)
    return dataclasses.replace(scene, meshes=meshes, lamps=lamps, world_from_cam=n(scene.world_from_cam),
                               sigma_a=n(scene.sigma_a), sun_irradiance_rgb=n(scene.sun_irradiance_rgb))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), vertices=st.integers(1, 3000), most=st.integers(1, 8))
def test_last_bit_changes_of_every_float_keep_the_fingerprint_and_change_the_digest(seed, vertices, most):
    scene = random_scene(seed, vertices)
    other = nudge_scene(scene, np.random.default_rng(seed + 1), most)
    assert fingerprints_agree(scene_fingerprint(scene), scene_fingerprint(other))
    if any(not np.array_equal(a, b) for a, b in zip(_scene_arrays(scene).values(), _scene_arrays(other).values())):
        assert scene_digest(other) != scene_digest(scene)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), vertices=st.integers(1, 3000), pick=st.integers(0, 10**9),
       over=st.floats(1.5, 1e6))
def test_one_value_moved_past_its_tolerance_changes_the_fingerprint(seed, vertices, pick, over):
    """The tolerance: rtol x (the larger of its run's magnitude and the array's mean run magnitude) + atol, on each
    run's sum and sum of magnitudes. A value moved by `over` times it (away from zero, so its magnitude moves too)
    is seen."""
    scene = random_scene(seed, vertices)
    fp = scene_fingerprint(scene)
    floats = [k for k, a in _scene_arrays(scene).items() if a.dtype.kind == "f" and k.startswith("mesh")]
    name = floats[pick % len(floats)]
    mesh = scene.meshes[int(name[4])]
    field = name.split("_", 1)[1]
    a = np.asarray(getattr(mesh, field)).copy()
    i = pick % a.size
    runs = np.array_split(np.arange(a.size), min(16, a.size))
    run = next(k for k, r in enumerate(runs) if i in r)
    mags = np.array(fp[name][3])
    tol = FINGERPRINT_RTOL * max(mags[run], mags.mean()) + FINGERPRINT_ATOL
    flat = a.reshape(-1)
    flat[i] = np.float32(flat[i] + np.copysign(over * tol, flat[i] if flat[i] != 0 else 1.0))
    moved = dataclasses.replace(scene, meshes=tuple(dataclasses.replace(m, **{field: a}) if m is mesh else m
                                                    for m in scene.meshes))
    assert not fingerprints_agree(fp, scene_fingerprint(moved))


def test_faces_ids_vertices_lamps_scalars_dtypes_shapes_and_names_are_seen():
    scene = random_scene(3, 50)
    fp = scene_fingerprint(scene)
    m = scene.meshes[0]
    for change in ({"faces": m.faces[::-1].copy()}, {"instance_id": 7}, {"vertices": m.vertices[:-1]},
                   {"vertices": m.vertices.astype(np.float64) + 1e-3}):
        other = dataclasses.replace(scene, meshes=(dataclasses.replace(m, **change),) + scene.meshes[1:])
        assert not fingerprints_agree(fp, scene_fingerprint(other)), change
    assert not fingerprints_agree(fp, scene_fingerprint(dataclasses.replace(scene, lamps=())))
    assert not fingerprints_agree(fp, scene_fingerprint(dataclasses.replace(scene, g=0.9)))
    for name, entry in fp.items():  # as exports of another version would store them
        assert not fingerprints_agree(fp, {**fp, name: ["<f2", *entry[1:]]}), name
        assert not fingerprints_agree(fp, {**fp, name: [entry[0], [*entry[1], 1], *entry[2:]]}), name
    assert not fingerprints_agree(fp, {k: v for k, v in fp.items() if k != "g"})
    assert fingerprints_agree(fp, scene_fingerprint(scene))


def test_a_reference_carries_its_fingerprint_through_its_file_a_merge_and_a_stamp(tmp_path):
    scene = random_scene(5, 40)
    h = np.ones((2, 2, 3), np.float32)
    plain = Reference((h, h), 10, "llvm_ad_rgb", 1.0, "cpu", scene_digest(scene), (0,))
    save_reference(plain, tmp_path / "a.ref.npz")
    assert load_reference(tmp_path / "a.ref.npz").scene_fingerprint is None
    other = nudge_scene(scene, np.random.default_rng(0), 2)
    assert scene_digest(other) != scene_digest(scene)
    assert not same_scene(plain, other)  # without a fingerprint, only the digest ties it
    with pytest.raises(ValueError, match="rendered for another scene"):
        stamp_fingerprint(tmp_path / "a.ref.npz", other)
    stamp_fingerprint(tmp_path / "a.ref.npz", scene)
    back = load_reference(tmp_path / "a.ref.npz")
    assert back.scene_fingerprint == scene_fingerprint(scene) and back.scene_sha256 == plain.scene_sha256
    np.testing.assert_array_equal(back.halves[0], h)
    assert same_scene(back, scene) and same_scene(back, other)
    assert not same_scene(back, dataclasses.replace(scene, g=0.9))
    merged = merge(back, dataclasses.replace(plain, seed_bases=(1,)))
    assert merged.scene_fingerprint == back.scene_fingerprint
    save_reference(merged, tmp_path / "m.ref.npz")
    assert load_reference(tmp_path / "m.ref.npz").scene_fingerprint == back.scene_fingerprint


def test_every_stored_reference_carries_a_fingerprint():
    paths = sorted(STORED.glob(f"*{REF_SUFFIX}"))
    assert len(paths) >= 20
    for path in paths:
        fp = load_reference(path).scene_fingerprint
        assert fp is not None and any(k.endswith("_vertices") for k in fp), path.name
