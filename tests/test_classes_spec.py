"""The spec's target classes and label filters (seasynth.service.spec.targets): one mapping is a list of one class
with the same digest and dump as before classes, lists round-trip, names are unique, limits hold."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import DatasetSpec, parse_spec, spec_digest
from seasynth.service.spec.scene import MAX_OBJECTS
from seasynth.service.spec.targets import Buried, InWater, Labels, Seabed

KINDS = ("urchin", "rock", "coral", "seaweed", "clam")


def refusal(data: dict) -> list[str]:
    with pytest.raises(SpecError) as err:
        parse_spec(data)
    return str(err.value).splitlines()[1:]


PLACEMENTS = st.one_of(
    st.just("seabed"), st.just({"kind": "seabed"}), st.just("buried"), st.just("water"),
    st.builds(lambda lo, w: {"kind": "buried", "sunk_fraction": [lo, lo + w]}, st.floats(0, 0.5), st.floats(0, 0.5)),
    st.builds(lambda lo, w, n: {"kind": "water", "height_m": [lo, lo + w], "school": {"size": [1, n]}},
              st.floats(0, 2), st.floats(0, 2), st.integers(1, 3)),
)
CLASSES = st.lists(
    st.fixed_dictionaries({
        "class_name": st.text(st.characters(categories=("L", "N", "P")), min_size=1, max_size=12),
        "assets": st.lists(st.sampled_from(KINDS).map(lambda k: {"procedural": k}), min_size=1, max_size=3),
        "count": st.tuples(st.integers(0, 3), st.integers(0, 3)).map(lambda t: [t[0], t[0] + t[1]]),
        "placement": PLACEMENTS}),
    min_size=1, max_size=6, unique_by=lambda c: c["class_name"])


@settings(max_examples=200, deadline=None)
@given(classes=CLASSES)
def test_class_lists_round_trip_through_their_dump_and_keep_their_order(classes):
    spec = parse_spec({"targets": classes})
    assert spec.class_names == tuple(c["class_name"] for c in classes)
    for full in (spec.model_dump(mode="json"), spec.model_dump(mode="json", exclude_defaults=True)):
        assert parse_spec(json.loads(json.dumps(full))) == spec
    kinds = [{"seabed": Seabed, "buried": Buried, "water": InWater}[
        c["placement"] if isinstance(c["placement"], str) else c["placement"]["kind"]] for c in classes]
    assert [type(c.placement) for c in spec.targets] == kinds
    assert spec.most_targets() == sum(c.most_objects() for c in spec.targets)


@settings(max_examples=100, deadline=None)
@given(name=st.text(st.characters(categories=("L", "N")), min_size=1, max_size=12),
       count=st.tuples(st.integers(0, 8), st.integers(0, 8)).map(sorted))
def test_one_mapping_is_a_list_of_one_class_with_the_dump_and_digest_of_the_mapping(name, count):
    mapping = {"class_name": name, "count": list(count), "assets": [{"procedural": "clam"}]}
    one, listed = parse_spec({"targets": mapping}), parse_spec({"targets": [mapping]})
    assert one == listed and len(one.targets) == 1 and isinstance(one.targets[0].placement, Seabed)
    assert spec_digest(one) == spec_digest(listed)
    # Dumped as the mapping, with no placement key: records of specs written before classes keep their bytes.
    dumped = one.model_dump(mode="json")["targets"]
    assert isinstance(dumped, dict) and "placement" not in dumped and dumped["class_name"] == name


def test_the_default_spec_digest_and_dump_are_those_before_classes():
    # The digest of the default spec as recorded by 0.7.0 (before target classes and label filters).
    assert spec_digest(DatasetSpec()) == "e74fb2b9f6968cd68461282fd938667a209821e6518576ed507d6d4a56b6179c"
    assert "targets" not in DatasetSpec().model_dump(exclude_defaults=True)
    assert DatasetSpec().model_dump(mode="json")["targets"] == {
        "class_name": "Urchin", "assets": [{"path": None, "asset_id": None, "procedural": "urchin", "variants": 8}],
        "count": [3, 8], "scale": [0.8, 1.25]}
    assert DatasetSpec().labels == Labels() and not Labels().filters


def test_a_yaml_targets_section_left_empty_is_the_default_class(tmp_path):
    from seasynth.service.spec.dataset import load_spec

    (tmp_path / "s.yaml").write_text("targets:\n  # nothing yet\n")
    assert load_spec(tmp_path / "s.yaml").targets == DatasetSpec().targets
    (tmp_path / "l.yaml").write_text("targets:\n  - class_name: A\n    placement: water\n  - class_name: B\n")
    spec = load_spec(tmp_path / "l.yaml")
    assert spec.class_names == ("A", "B") and isinstance(spec.targets[0].placement, InWater)
    # Relative asset paths of every class resolve against the spec file's folder, as a single class's do.
    (tmp_path / "p.yaml").write_text("targets:\n  - {class_name: A, assets: [{path: a.glb}]}\n"
                                     "  - {class_name: B, assets: [{procedural: rock}, {path: sub/b.obj}]}\n")
    spec = load_spec(tmp_path / "p.yaml")
    assert [a.path for c in spec.targets for a in c.assets] == [str(tmp_path / "a.glb"), None,
                                                                 str(tmp_path / "sub/b.obj")]
    assert [f for f, _ in spec.file_refs()] == ["targets.0.assets.0", "targets.1.assets.1"]


def test_repeated_class_names_are_refused_naming_them():
    (line,) = refusal({"targets": [{"class_name": "A"}, {"class_name": "B"}, {"class_name": "A"}]})
    assert line == "targets: class names must be unique; 'A' repeated"


def test_dontcare_is_no_class_name():
    (line,) = refusal({"targets": {"class_name": "DontCare"}})
    assert line.startswith("targets.class_name: 'DontCare' is KITTI's type of the regions to ignore")
    (line,) = refusal({"targets": [{"class_name": "A"}, {"class_name": "DontCare"}]})
    assert line.startswith("targets.1.class_name: ")


def test_fields_are_named_as_written_mapping_or_list():
    (line,) = refusal({"targets": {"count": [3, 1]}})
    assert line == "targets.count: min 3 > max 1"
    (line,) = refusal({"targets": [{"class_name": "A"}, {"class_name": "B", "count": [3, 1]}]})
    assert line == "targets.1.count: min 3 > max 1"
    (line,) = refusal({"targets": [{"class_name": "A", "placement": "floating"}]})
    assert line.startswith("targets.0.placement: ")


def test_the_targets_of_a_frame_are_limited_per_role_over_all_classes_and_schools():
    half = MAX_OBJECTS // 2
    ok = parse_spec({"targets": [{"class_name": "A", "count": [0, half]}, {"class_name": "B", "count": [0, half]}]})
    assert ok.most_targets() == MAX_OBJECTS
    (line,) = refusal({"targets": [{"class_name": "A", "count": [0, half]},
                                   {"class_name": "B", "count": [0, half + 1]}]})
    assert line == f"targets: the classes' count maxima add up to {MAX_OBJECTS + 1} targets a frame, over the " \
                   f"limit of {MAX_OBJECTS}"
    (line,) = refusal({"targets": {"count": [0, 9], "placement": {"kind": "water", "school": {"size": [1, 8]}}}})
    assert line.startswith("targets: count max 9 schools of up to 8 is 72 objects, over the limit of 64")
    assert refusal({"targets": [{"class_name": str(k), "count": [0, 0]} for k in range(65)]})[0].startswith(
        "targets: List should have at most 64 items")


@pytest.mark.parametrize("labels, field", [({"min_visible_px": 0}, "min_visible_px"),
                                           ({"min_visible_fraction": 1.5}, "min_visible_fraction"),
                                           ({"min_visible_fraction": "0.5"}, "min_visible_fraction"),
                                           ({"min_visible_px": 2.0}, "min_visible_px"),
                                           ({"min_px": 3}, "min_px")])
def test_label_filters_are_checked_naming_the_field(labels, field):
    (line,) = refusal({"labels": labels})
    assert line.startswith(f"labels.{field}: ")


def test_label_filters_filter_only_when_set():
    assert parse_spec({"labels": {"min_visible_px": 2}}).labels.filters
    assert parse_spec({"labels": {"min_visible_fraction": 0.01}}).labels.filters
    assert not parse_spec({"labels": {"min_visible_px": 1, "min_visible_fraction": 0}}).labels.filters
