"""Tests of the procedural marine animals and litter (worker/scene/assets/marine.py, litter.py): closed, outward,
sized as documented, deterministic per (kind, variant), within their triangle budgets; their labels through the
renderer: test_vocabulary_labels.py."""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
from pathlib import Path
from typing import get_args

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.spec.scene import ProceduralTarget
from seasynth.worker.scene.assets.procedural import PROCEDURAL, procedural_asset
from seasynth.worker.scene.assets.textures import FAMILIES
from seasynth.worker.scene.materials import ASSET_FAMILY

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "spec-guide.md"
# kind: (largest bounding-box extent in metres, as docs/spec-guide.md's table states it; triangle budget)
VOCABULARY = {
    "starfish": ((0.06, 0.30), 2016),
    "sea_cucumber": ((0.10, 0.36), 1450),
    "scallop": ((0.05, 0.16), 1536),
    "anemone": ((0.03, 0.30), 2500),
    "sponge": ((0.10, 0.50), 1280),
    "fish": ((0.09, 0.60), 680),
    "plastic_bottle": ((0.15, 0.34), 828),
    "glass_bottle": ((0.19, 0.35), 636),
    "can": ((0.09, 0.17), 572),
    "tyre": ((0.55, 0.83), 2400),
    "rope": ((0.15, 1.25), 1260),
    "net": ((0.18, 1.10), 2208),
    "cinder_block": ((0.38, 0.46), 1224),
    "pipe": ((0.20, 1.20), 576),
}
KINDS = sorted(VOCABULARY)
variants = st.integers(0, 10**6)
SOME = settings(max_examples=12, deadline=None)


def mesh_bytes(mesh) -> bytes:
    return mesh.vertices.tobytes() + mesh.faces.tobytes() + mesh.visual.vertex_colors.tobytes()


def winding_number(mesh, points: np.ndarray) -> np.ndarray:
    """(n,) generalised winding numbers of `points: (n, 3)`: 1 inside a closed outward mesh, 0 outside."""
    tri = mesh.vertices[mesh.faces][None] - points[:, None, None]  # (n, F, 3, 3)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("nfi,nfi->nf", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("nfi,nfi->nf", a, b) * lc + np.einsum("nfi,nfi->nf", b, c) * la \
        + np.einsum("nfi,nfi->nf", c, a) * lb
    return (2.0 * np.arctan2(det, den)).sum(axis=1) / (4.0 * np.pi)


def test_every_kind_is_registered_in_the_spec_and_has_a_texture_family():
    assert set(VOCABULARY) | {"urchin", "rock", "coral", "seaweed", "clam"} == set(PROCEDURAL)
    assert list(get_args(ProceduralTarget)) == list(PROCEDURAL)
    assert set(ASSET_FAMILY) == set(PROCEDURAL) and set(ASSET_FAMILY.values()) <= set(FAMILIES)


def test_the_guide_s_table_states_the_tested_sizes_and_the_texture_families():
    rows = re.findall(r"^\| `(\w+)` \| [^|]+ \| (\d+)-(\d+) cm \| (\w+) \| (\w+) \|$", GUIDE.read_text(), re.MULTILINE)
    assert [kind for kind, *_ in rows] == list(PROCEDURAL)
    stated = {kind: (int(lo) / 100, int(hi) / 100) for kind, lo, hi, *_ in rows}
    assert {kind: stated[kind] for kind in VOCABULARY} == {kind: size for kind, (size, _) in VOCABULARY.items()}
    assert {watertight for *_, watertight, _ in rows} == {"yes"}
    assert {kind: family for kind, *_, family in rows} == ASSET_FAMILY


@pytest.mark.parametrize("kind", KINDS)
@SOME
@given(variant=variants)
def test_closed_outward_sized_and_within_budget(kind, variant):
    mesh = procedural_asset(kind, variant).mesh
    (lo, hi), budget = VOCABULARY[kind]
    v = mesh.vertices
    assert v.dtype == np.float64 and np.all(np.isfinite(v)) and not v.flags.writeable
    assert mesh.is_watertight and mesh.is_winding_consistent
    parts = mesh.split(only_watertight=False)
    assert all(p.is_watertight for p in parts) and min(p.volume for p in parts) > 0.0  # each closed, outward
    assert mesh.area_faces.min() > 1e-10  # no degenerate faces
    assert lo <= np.ptp(v, axis=0).max() <= hi
    assert len(mesh.faces) <= budget
    lo3, hi3 = v.min(axis=0), v.max(axis=0)
    centre = (lo3 + hi3) / 2.0
    if kind == "fish":  # hangs in the water column: its origin is its centre
        np.testing.assert_allclose(centre, 0.0, atol=1e-9)
    else:  # rests on the seabed
        assert lo3[2] == 0.0
        np.testing.assert_allclose(centre[:2], 0.0, atol=1e-9)
    colours = mesh.visual.vertex_colors
    assert colours.shape == (len(v), 4) and colours.dtype == np.uint8 and np.all(colours[:, 3] == 255)


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=5, deadline=None)
@given(variant=variants)
def test_a_variant_is_the_same_bytes_every_time_and_its_neighbour_differs(kind, variant):
    first = procedural_asset(kind, variant)
    procedural_asset.cache_clear()
    again = procedural_asset(kind, variant)
    assert again is not first and mesh_bytes(again.mesh) == mesh_bytes(first.mesh)
    assert mesh_bytes(procedural_asset(kind, variant + 1).mesh) != mesh_bytes(first.mesh)
    assert (again.key, again.source) == (f"procedural/{kind}/{variant}", f"procedural:{kind}#{variant}")


def digest(kinds, variants) -> str:
    h = hashlib.sha256()
    for kind in kinds:
        for variant in variants:
            h.update(mesh_bytes(procedural_asset(kind, variant).mesh))
    return h.hexdigest()


def test_a_fresh_process_makes_the_same_bytes():
    code = "from tests.test_vocabulary import digest, KINDS; print(digest(KINDS, range(3)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == digest(KINDS, range(3))


@settings(max_examples=8, deadline=None)
@given(variant=variants)
def test_a_fish_has_its_nose_along_plus_x(variant):
    mesh = procedural_asset("fish", variant).mesh
    v = mesh.vertices
    lo, hi = v[:, 0].min(), v[:, 0].max()
    tail = v[v[:, 0] < lo + 0.1 * (hi - lo)]
    across = np.ptp(tail[:, 1:], axis=0)
    assert across.min() < 0.005 and across.max() > 0.1 * (hi - lo)  # the rear tenth is the tail fin: thin and broad
    eyes = v[np.all(mesh.visual.vertex_colors[:, :3] < 20, axis=1)]  # the only near-black vertices
    assert len(eyes) == 2 * 42 and eyes[:, 0].min() > lo + 0.75 * (hi - lo)


@settings(max_examples=10, deadline=None)
@given(variant=variants)
def test_a_starfish_has_four_to_six_arms(variant):
    v = procedural_asset("starfish", variant).mesh.vertices
    angle = np.arctan2(v[:, 1], v[:, 0])
    radius = np.hypot(v[:, 0], v[:, 1])
    bins = np.full(72, 0.0)
    np.maximum.at(bins, ((angle + np.pi) / (2 * np.pi) * 72).astype(int) % 72, radius)
    high = bins > 0.5 * (bins.min() + bins.max())
    arms = np.count_nonzero(high & ~np.roll(high, 1))  # runs of long radius around the disc
    assert arms in (4, 5, 6)


@settings(max_examples=10, deadline=None)
@given(variant=variants)
def test_a_scallop_has_a_straight_hinge_with_ears(variant):
    mesh = procedural_asset("scallop", variant).mesh
    v = mesh.vertices
    rows, count = np.unique(np.round(v[:, 1:], 9), axis=0, return_counts=True)
    hinge = v[np.all(np.round(v[:, 1:], 9) == rows[np.argmax(count)], axis=1)]  # the most vertices on one line along x
    assert len(hinge) >= 6 and np.ptp(hinge[:, 0]) >= 0.3 * np.ptp(v[:, 0])


@pytest.mark.parametrize("kind", ["pipe", "tyre", "cinder_block"])
@settings(max_examples=6, deadline=None)
@given(variant=variants)
def test_holes_go_through(kind, variant):
    """The bore of a pipe, the middle of a tyre and a cinder block's first core are outside the solid, a point just
    inside its wall inside."""
    mesh = procedural_asset(kind, variant).mesh
    v = mesh.vertices
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2.0
    if kind == "cinder_block":  # the end shell is 2.5-3.5 cm thick, the first core runs past 7.5 cm (along x), from
        # the end face where the probes' line meets it (a worn block's lowest x can be a corner's, 1.3 cm before it)
        xs = lo[0] + np.arange(0.0, 0.05, 5e-4)
        inside = winding_number(mesh, np.column_stack([xs, np.full_like(xs, centre[1]), np.full_like(xs, centre[2])]))
        x0 = float(xs[np.argmax(inside > 0.5)])
        points = np.array([[x0 + 0.075, centre[1], centre[2]], [x0 + 0.012, centre[1], centre[2]]])
    else:  # the middle, and just below the top of the wall
        points = np.array([centre, v[np.argmax(v[:, 2])] - [0.0, 0.0, 1e-4]])
    assert winding_number(mesh, points) == pytest.approx([0.0, 1.0], abs=1e-6)
