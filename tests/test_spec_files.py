"""Spec files (YAML and JSON, paths relative to the file) and dotted-key overrides."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from spec_helpers import EXAMPLE, MAPPING

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import (
    DatasetSpec,
    apply_overrides,
    load_spec,
    parse_spec,
    read_spec_file,
    resolve_paths,
)

# --- spec files ------------------------------------------------------------------------------------------------


def test_yaml_yml_and_json_files_read_identically(tmp_path):
    for name in ("spec.yaml", "spec.yml", "SPEC.YAML"):
        (tmp_path / name).write_text(yaml.safe_dump(MAPPING))
    (tmp_path / "spec.json").write_text(json.dumps(MAPPING))
    specs = [load_spec(tmp_path / n) for n in ("spec.yaml", "spec.yml", "SPEC.YAML", "spec.json")]
    assert all(s == parse_spec(MAPPING) for s in specs)
    assert specs[0] != DatasetSpec()
    assert read_spec_file(tmp_path / "spec.yaml") == read_spec_file(tmp_path / "spec.json") == MAPPING


@pytest.mark.parametrize("name", ["spec.toml", "spec.txt", "spec"])
def test_other_suffixes_are_refused_naming_the_file(tmp_path, name):
    path = tmp_path / name
    path.write_text("{}")
    with pytest.raises(SpecError) as info:
        load_spec(path)
    assert str(info.value) == f"{path}: spec files must end in .yaml, .yml or .json"


@pytest.mark.parametrize(
    ("name", "text", "kind"),
    [("bad.yaml", "camera: [1, 2\n", "YAML"), ("bad.yml", "a: b: c\n", "YML"), ("bad.json", '{"seed": 1,', "JSON")],
)
def test_malformed_file_is_refused_naming_the_file(tmp_path, name, text, kind):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(SpecError) as info:
        load_spec(path)
    assert str(info.value).startswith(f"{path}: not valid {kind}: ")


def test_missing_file_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "nowhere.yaml"
    with pytest.raises(SpecError) as info:
        load_spec(path)
    assert str(info.value).startswith(f"{path}: cannot read spec file (")


@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        ("list.yaml", b"- seed\n- frames\n", "the spec must be a mapping, got list"),
        ("number.json", b"7", "the spec must be a mapping, got int"),
        ("latin1.yaml", b"targets: {class_name: \xe9}\n", "not UTF-8 text"),
    ],
)
def test_file_that_is_not_a_mapping_or_not_text_is_refused_naming_the_file(tmp_path, name, content, expected):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(SpecError) as info:
        load_spec(path)
    assert str(info.value).startswith(f"{path}: {expected}")


@pytest.mark.parametrize(
    ("text", "path"),
    [
        ("targets: 5\n", "targets"),
        ("targets: {assets: 5}\n", "targets.assets"),
        ("terrain: [mesh]\n", "terrain"),
        ("targets: {class_name: 2024-01-01}\n", "targets.class_name"),  # YAML reads a date, not a string
    ],
)
def test_ill_typed_sections_in_a_file_are_refused_naming_file_and_field(tmp_path, text, path):
    spec_file = tmp_path / "s.yaml"
    spec_file.write_text(text)
    with pytest.raises(SpecError) as info:
        load_spec(spec_file)
    header, line = str(info.value).splitlines()
    assert header == f"{spec_file}: invalid spec"
    assert line.startswith(f"{path}: ")


def test_invalid_value_in_a_file_is_refused_naming_file_and_field(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("camera:\n  width: 5000\n")
    with pytest.raises(SpecError) as info:
        load_spec(path)
    header, line = str(info.value).splitlines()
    assert header == f"{path}: invalid spec"
    assert line.startswith("camera.width: ")


@pytest.mark.parametrize("text", ["", "\n", "# only a comment\n", "---\n"])
def test_empty_yaml_file_gives_the_defaults(tmp_path, text):
    path = tmp_path / "empty.yaml"
    path.write_text(text)
    assert load_spec(path) == DatasetSpec()


def test_a_yaml_section_with_nothing_under_it_is_at_its_defaults_with_or_without_overrides(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("frames: 7\ncamera:\n#  width: 320\nsensors:\n  fls:\n  dvl:\n    enabled: true\n")
    spec = load_spec(path)
    assert spec == parse_spec({"frames": 7, "sensors": {"dvl": {"enabled": True}}})
    assert spec.camera == DatasetSpec().camera and spec.sensors.fls == DatasetSpec().sensors.fls
    # the same file with an override inside the empty section: that field set, the rest at its defaults
    assert load_spec(path, {"camera.width": 320}) == parse_spec(
        {"frames": 7, "camera": {"width": 320}, "sensors": {"dvl": {"enabled": True}}})
    # null stays refused where it is not a section, and in JSON (which has no empty value to forgive)
    path.write_text("frames:\n")
    with pytest.raises(SpecError, match="frames: "):
        load_spec(path)
    (tmp_path / "s.json").write_text('{"camera": null}')
    with pytest.raises(SpecError, match="camera: "):
        load_spec(tmp_path / "s.json")


def test_relative_asset_paths_resolve_against_the_spec_files_folder(tmp_path):
    folder = tmp_path / "specs"
    folder.mkdir()
    absolute = str(tmp_path / "abs" / "tex.png")
    asset_id = "ab" * 32
    (folder / "s.yaml").write_text(
        yaml.safe_dump(
            {
                "targets": {"assets": [{"path": "meshes/u.obj"}, {"asset_id": asset_id}]},
                "distractors": {"assets": [{"path": "../d.ply"}, {"procedural": "rock"}]},
                "terrain": {"mesh": {"path": "t.glb"}, "texture": {"path": absolute}},
            }
        )
    )
    spec = load_spec(folder / "s.yaml")
    assert [(field, ref.path) for field, ref in spec.file_refs()] == [
        ("targets.assets.0", str((folder / "meshes" / "u.obj").resolve())),
        ("targets.assets.1", None),
        ("distractors.assets.0", str((tmp_path / "d.ply").resolve())),
        ("terrain.mesh", str((folder / "t.glb").resolve())),
        ("terrain.texture", absolute),
    ]
    assert spec.targets[0].assets[1].asset_id == asset_id


def test_resolve_paths_returns_a_copy():
    data = {"targets": {"assets": [{"path": "u.obj"}]}, "terrain": {"mesh": {"path": "/m.glb"}}}
    before = json.loads(json.dumps(data))
    out = resolve_paths(data, Path("/base"))
    assert data == before
    assert out == {"targets": {"assets": [{"path": "/base/u.obj"}]}, "terrain": {"mesh": {"path": "/m.glb"}}}


# --- overrides -------------------------------------------------------------------------------------------------


def test_apply_overrides_sets_dotted_keys_skips_none_and_leaves_input_alone():
    data = {"camera": {"width": 640, "hfov_deg": 75}, "seed": 3}
    out = apply_overrides(
        data, {"camera.width": 64, "camera.height": None, "frames": 3, "outputs.depth": True, "seed": None}
    )
    assert out == {"camera": {"width": 64, "hfov_deg": 75}, "seed": 3, "frames": 3, "outputs": {"depth": True}}
    assert data == {"camera": {"width": 640, "hfov_deg": 75}, "seed": 3}


def test_apply_overrides_seed_zero_is_set_not_skipped():
    assert apply_overrides({"seed": 9}, {"seed": 0}) == {"seed": 0}


def test_apply_overrides_fills_an_empty_section():
    # `camera:` with nothing under it reads as null.
    assert apply_overrides({"camera": None}, {"camera.width": 64}) == {"camera": {"width": 64}}


def test_apply_overrides_into_a_non_mapping_is_refused_naming_the_key(tmp_path):
    with pytest.raises(SpecError) as info:
        apply_overrides({"camera": 5}, {"camera.width": 64})
    assert str(info.value) == "camera: must be a mapping to set camera.width"
    path = tmp_path / "s.yaml"
    path.write_text("camera: 5\n")
    with pytest.raises(SpecError) as info:
        load_spec(path, {"camera.width": 64})
    assert str(info.value) == f"{path}: camera: must be a mapping to set camera.width"


def test_invalid_override_is_refused_naming_the_field():
    with pytest.raises(SpecError) as info:
        load_spec(EXAMPLE, {"camera.width": 5000, "frames": None})
    header, line = str(info.value).splitlines()
    assert header == f"{EXAMPLE}: invalid spec"
    assert line.startswith("camera.width: ")
