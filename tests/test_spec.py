"""The dataset spec: contract keys and defaults, the example, digests and seeds."""

from __future__ import annotations

import json
import math

import pytest
import yaml
from hypothesis import assume, given
from hypothesis import strategies as st
from spec_helpers import EXAMPLE, MAPPING, refusal

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import DatasetSpec, apply_overrides, load_spec, parse_spec, spec_digest
from seasynth.service.spec.scene import MAX_SIDE

# --- defaults and the contract's key names -------------------------------------------------------------------


def test_empty_spec_is_the_default_spec():
    assert parse_spec({}) == DatasetSpec()


def test_contract_keys_and_defaults():
    spec = DatasetSpec()
    assert (spec.seed, spec.frames, spec.shard_size) == (0, 100, 50)
    assert (spec.camera.width, spec.camera.height) == (640, 480)
    assert spec.outputs.model_dump() == {
        "labels": True,
        "meta": True,
        "depth": False,
        "instance": False,
        "semantic": False,
        "clean": False,
        "range": False,
        "coco": False,
        "yolo": False,
        "mcap": False,
        "split": (0.8, 0.1, 0.1),
        "image_format": "png",
        "jpeg_quality": 95,
    }
    # The contract names are the keys a spec file uses: each is accepted and read back as written.
    written = {
        "seed": 5,
        "frames": 7,
        "shard_size": 3,
        "camera": {"width": 96, "height": 64},
        "outputs": {"labels": False, "meta": False, "depth": True, "instance": True, "semantic": False, "clean": True,
                    "range": True,
                    "coco": False, "yolo": False, "mcap": False, "split": (0.5, 0.25, 0.25),
                    "image_format": "jpeg", "jpeg_quality": 80},
    }
    dumped = parse_spec(written).model_dump()
    for key in ("seed", "frames", "shard_size"):
        assert dumped[key] == written[key]
    assert (dumped["camera"]["width"], dumped["camera"]["height"]) == (96, 64)
    assert dumped["outputs"] == written["outputs"]


def test_default_spec_round_trips_through_its_json_dump():
    spec = DatasetSpec()
    assert parse_spec(json.loads(spec.model_dump_json())) == spec


EXAMPLES = sorted(EXAMPLE.parent.glob("*.yaml"))
INTERVAL = st.floats(0.02, 0.5).map(lambda v: {"min": [v, v / 2, v / 4], "max": [2 * v, v, v / 2]})
WATER = st.fixed_dictionaries({}, optional={
    "enabled": st.booleans(), "model": st.sampled_from(["paper", "physical", None]),
    "jerlov": st.lists(st.sampled_from(["I", "II", "III", "1C", "3C", "5C", "9C"]), max_size=3),
    "solved_column": st.booleans(), "forward_scatter": st.booleans(), "beta_D": INTERVAL, "B_inf": INTERVAL,
    "absorption": INTERVAL, "scattering": INTERVAL, "depth_m": st.sampled_from([[2.0, 4.0], [30.0, 200.0]]),
    "particles": st.fixed_dictionaries({"enabled": st.booleans()})})
SECTIONS = st.fixed_dictionaries({}, optional={
    "water": WATER, "terrain": st.fixed_dictionaries({}, optional={"far_field": st.booleans(),
                                                                    "styles": st.sampled_from([["sand"], ["rock"]])}),
    "lighting": st.fixed_dictionaries({}, optional={"shadows": st.booleans(), "lamps": st.sampled_from(
        [[], [{"intensity": [20.0, 40.0]}]])}),
    "outputs": st.fixed_dictionaries({}, optional={k: st.booleans() for k in ("depth", "range", "coco", "clean")}),
    "quality": st.sampled_from(["draft", "default"])})


@given(base=st.sampled_from([{}, MAPPING, *EXAMPLES]), sections=SECTIONS)
def test_every_valid_spec_reads_back_from_its_dumps_as_itself(base, sections):
    """A spec's full, default-free and None-free dumps (what the service stores, digests and the benches write) each
    parse back to the spec they came from, with its digest and its resolved water model: a field whose default only
    applies to some specs (water.solved_column) must not refuse the dump of the others."""
    data = yaml.safe_load(base.read_text()) if hasattr(base, "read_text") else dict(base)
    data = {**data, **{k: {**data.get(k, {}), **v} if isinstance(v, dict) else v for k, v in sections.items()}}
    try:
        spec = parse_spec(data)
    except SpecError:
        assume(False)
    for dump in ({}, {"exclude_defaults": True}, {"exclude_none": True}):
        back = parse_spec(json.loads(spec.model_dump_json(**dump)))
        assert back == spec, dump
        assert spec_digest(back) == spec_digest(spec), dump
        assert back.water.resolved_model == spec.water.resolved_model, dump


# --- the example ---------------------------------------------------------------------------------------------


def test_example_is_procedural_with_water_and_fov_camera():
    spec = load_spec(EXAMPLE)
    assert spec.file_refs() == []
    assert all(a.procedural is not None and a.path is None and a.asset_id is None for a in spec.asset_refs())
    assert [a.procedural for a in spec.targets[0].assets] == ["urchin"]
    assert {a.procedural for a in spec.distractors.assets} == {"rock", "coral", "seaweed", "clam"}
    assert spec.terrain.mesh is None and spec.terrain.texture is None
    assert spec.water.enabled is True
    assert spec.camera.hfov_deg == 75.0 and spec.camera.intrinsics is None
    assert (spec.seed, spec.frames, spec.shard_size) == (7, 20, 10)


@pytest.mark.parametrize(("width", "height"), [(64, 48), (1920, 1080), (8, 8), (MAX_SIDE, 96)])
def test_example_resized_by_width_and_height_alone_stays_valid(width, height):
    base = load_spec(EXAMPLE)
    spec = load_spec(EXAMPLE, {"camera.width": width, "camera.height": height})
    assert (spec.camera.width, spec.camera.height) == (width, height)
    # Nothing but the two overridden keys changed.
    expected = base.model_dump()
    expected["camera"].update(width=width, height=height)
    assert spec.model_dump() == expected
    f = (width / 2) / math.tan(math.radians(75.0) / 2)
    assert spec.camera.K() == [[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]]


def test_intrinsics_camera_K_is_the_given_intrinsics():
    cam = parse_spec({"camera": {"intrinsics": {"fx": 500.0, "fy": 510.0, "cx": 319.5, "cy": 239.5}}}).camera
    assert cam.K() == [[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]]


# --- digests and seeds -----------------------------------------------------------------------------------------


def test_equal_specs_have_equal_digests(tmp_path):
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(MAPPING))
    (tmp_path / "a.json").write_text(json.dumps(MAPPING))
    assert spec_digest(load_spec(tmp_path / "a.yaml")) == spec_digest(load_spec(tmp_path / "a.json"))
    digest = spec_digest(DatasetSpec())
    assert digest == spec_digest(parse_spec({})) == spec_digest(parse_spec({"seed": 0, "camera": {"width": 640}}))
    assert len(digest) == 64 and set(digest) <= set("0123456789abcdef")


CHANGES = {
    "seed": 1,
    "frames": 101,
    "shard_size": 49,
    "quality": "high",
    "camera.width": 641,
    "camera.hfov_deg": 60.0,
    "camera.clip": [0.02, 299.0],
    "workspaces.camera": {"min": [-1.5, -3.0, 0.8], "max": [1.5, -1.0, 2.1]},
    "targets.class_name": "Echinoid",
    "targets.count": [3, 9],
    "targets.assets": [{"procedural": "urchin", "variants": 9}],
    "distractors.scale": [0.7, 1.5],
    "terrain.styles": ["sand"],
    "lighting.ambient": [0.15, 0.36],
    "water.enabled": False,
    "water.jerlov": ["II", "III", "3C"],
    "texture.bias": [-0.05, 0.04],
    "noise.gaussian_sigma": 0.01,
    "outputs.labels": False,
    "outputs.depth": True,
    "outputs.range": True,
}


def test_digest_changes_when_any_field_changes():
    digests = {"default": spec_digest(DatasetSpec())}
    for key, value in CHANGES.items():
        digests[key] = spec_digest(parse_spec(apply_overrides({}, {key: value})))
    assert len(set(digests.values())) == len(digests)


def test_seed_zero_is_a_seed_distinct_from_one():
    zero = parse_spec({"seed": 0})
    one = parse_spec({"seed": 1})
    assert zero.seed == 0 and one.seed == 1
    assert spec_digest(zero) != spec_digest(one)


@given(a=st.integers(0, 2**63 - 1), b=st.integers(0, 2**63 - 1))
def test_digest_equal_exactly_when_seeds_equal(a, b):
    assert (spec_digest(DatasetSpec(seed=a)) == spec_digest(DatasetSpec(seed=b))) == (a == b)


def test_seed_at_and_over_its_limit():
    assert parse_spec({"seed": 2**63 - 1}).seed == 2**63 - 1
    (line,) = refusal({"seed": 2**63})
    assert line.startswith("seed: ")


def test_export_outputs_default_off_and_leave_digests_alone():
    """outputs.coco, yolo, mcap and split are new fields at their defaults: a spec written before them keeps its
    digest (and so its dataset records), and `exports` lists the formats switched on in a fixed order."""
    assert DatasetSpec().outputs.exports == ()
    assert spec_digest(parse_spec({"outputs": {"coco": False, "split": [0.8, 0.1, 0.1]}})) == spec_digest(DatasetSpec())
    on = parse_spec({"outputs": {"mcap": True, "coco": True, "split": [1, 0, 0]}})
    assert on.outputs.exports == ("coco", "mcap") and on.outputs.split == (1.0, 0.0, 0.0)
    assert spec_digest(on) != spec_digest(DatasetSpec())



def test_an_integer_is_a_float():
    assert parse_spec({"noise": {"gaussian_sigma": 0}, "terrain": {"size_m": 12}}).terrain.size_m == 12.0
