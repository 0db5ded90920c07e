"""The dataset spec: contract keys and defaults, refusals naming the field, spec files, overrides, digests, CLI exits."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from service.errors import SpecError
from service.spec import (
    MAX_FRAMES,
    DatasetSpec,
    apply_overrides,
    load_spec,
    parse_spec,
    read_spec_file,
    resolve_paths,
    spec_digest,
)
from service.spec_scene import MAX_ASSETS, MAX_OBJECTS, MAX_SIDE
from service.spec_types import MAX_CHOICES

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "urchins.yaml"


def refusal(data, source="spec") -> list[str]:
    """The lines of the SpecError that parse_spec raises for `data` (the header line checked and dropped)."""
    with pytest.raises(SpecError) as info:
        parse_spec(data, source=source)
    header, *lines = str(info.value).splitlines()
    assert header == f"{source}: invalid spec"
    return lines


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
        "clean": False,
        "range": False,
        "coco": False,
        "yolo": False,
        "mcap": False,
        "split": (0.8, 0.1, 0.1),
    }
    # The contract names are the keys a spec file uses: each is accepted and read back as written.
    written = {
        "seed": 5,
        "frames": 7,
        "shard_size": 3,
        "camera": {"width": 96, "height": 64},
        "outputs": {"labels": False, "meta": False, "depth": True, "instance": True, "clean": True, "range": True,
                    "coco": False, "yolo": False, "mcap": False, "split": (0.5, 0.25, 0.25)},
    }
    dumped = parse_spec(written).model_dump()
    for key in ("seed", "frames", "shard_size"):
        assert dumped[key] == written[key]
    assert (dumped["camera"]["width"], dumped["camera"]["height"]) == (96, 64)
    assert dumped["outputs"] == written["outputs"]


def test_default_spec_round_trips_through_its_json_dump():
    spec = DatasetSpec()
    assert parse_spec(json.loads(spec.model_dump_json())) == spec


# --- the example ---------------------------------------------------------------------------------------------


def test_example_is_procedural_with_water_and_fov_camera():
    spec = load_spec(EXAMPLE)
    assert spec.file_refs() == []
    assert all(a.procedural is not None and a.path is None and a.asset_id is None for a in spec.asset_refs())
    assert [a.procedural for a in spec.targets.assets] == ["urchin"]
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


# --- refusals, each naming the field by its dotted path --------------------------------------------------------

RGB_OK = [0.1, 0.1, 0.1]

REFUSED = [
    # min > max
    ({"targets": {"count": [5, 2]}}, "targets.count", "min 5 > max 2"),
    ({"targets": {"scale": [2.0, 1.0]}}, "targets.scale", "min 2.0 > max 1.0"),
    ({"lighting": {"sun_intensity": [2.0, 1.0]}}, "lighting.sun_intensity", "min 2.0 > max 1.0"),
    ({"camera": {"clip": [10.0, 1.0]}}, "camera.clip", "min 10.0 > max 1.0"),
    ({"camera": {"clip": [1.0, 1.0]}}, "camera.clip", "near 1.0 must be < far 1.0"),
    ({"texture": {"bias": [0.1, -0.1]}}, "texture.bias", "min 0.1 > max -0.1"),
    ({"workspaces": {"camera": {"min": [0, 0, 2], "max": [1, 1, 1]}}}, "workspaces.camera", "min z 2.0 > max z 1.0"),
    ({"water": {"beta_D": {"min": [0.2, 0.1, 0.1], "max": RGB_OK}}}, "water.beta_D", "channel R: min 0.2 > max 0.1"),
    # negative or zero sizes, counts and coefficients
    ({"terrain": {"size_m": -1.0}}, "terrain.size_m", "greater than 0"),
    ({"terrain": {"size_m": 0.0}}, "terrain.size_m", "greater than 0"),
    ({"terrain": {"relief_m": -0.1}}, "terrain.relief_m", "greater than or equal to 0"),
    ({"distractors": {"count": [-1, 3]}}, "distractors.count", "counts must be >= 0, got min -1"),
    ({"targets": {"scale": [0.0, 1.0]}}, "targets.scale", "must be > 0, got min 0.0"),
    ({"lighting": {"ambient": [-0.1, 0.2]}}, "lighting.ambient", "must be >= 0, got min -0.1"),
    ({"water": {"beta_D": {"min": [0.1, -0.1, 0.1], "max": RGB_OK}}}, "water.beta_D", "channel G: must be >= 0"),
    ({"water": {"beta_B": {"min": [0.1, 0.1, -0.5], "max": RGB_OK}}}, "water.beta_B", "channel B: must be >= 0"),
    ({"water": {"B_inf": {"min": [-0.01, 0.0, 0.0], "max": RGB_OK}}}, "water.B_inf", "channel R: must be >= 0"),
    ({"noise": {"gaussian_sigma": -0.01}}, "noise.gaussian_sigma", "greater than or equal to 0"),
    # documented limits
    ({"camera": {"width": 5000}}, "camera.width", f"less than or equal to {MAX_SIDE}"),
    ({"camera": {"height": MAX_SIDE + 1}}, "camera.height", f"less than or equal to {MAX_SIDE}"),
    ({"camera": {"width": 4}}, "camera.width", "greater than or equal to 8"),
    ({"frames": MAX_FRAMES + 1}, "frames", f"less than or equal to {MAX_FRAMES}"),
    ({"frames": 0}, "frames", "greater than or equal to 1"),
    ({"seed": -1}, "seed", "greater than or equal to 0"),
    ({"targets": {"count": [0, MAX_OBJECTS + 1]}}, "targets.count", f"over the limit of {MAX_OBJECTS} objects"),
    ({"camera": {"hfov_deg": 170.0}}, "camera.hfov_deg", "less than 170"),
    # not finite: NaN and inf would pass every bound check
    ({"camera": {"look_at_jitter_m": math.inf}}, "camera.look_at_jitter_m", "finite number"),
    ({"camera": {"intrinsics": {"fx": 1, "fy": 1, "cx": math.nan, "cy": 0}}}, "camera.intrinsics.cx", "finite"),
    ({"lighting": {"ambient": [0.1, math.inf]}}, "lighting.ambient.1", "finite number"),
    # unknown fields, top level and nested
    ({"frame": 10}, "frame", "Extra inputs are not permitted"),
    ({"camera": {"fov": 60}}, "camera.fov", "Extra inputs are not permitted"),
    ({"outputs": {"foo": True}}, "outputs.foo", "Extra inputs are not permitted"),
    # export formats: labels needed, the split validated as `seasynth export --split` is
    ({"outputs": {"labels": False, "coco": True}}, "outputs.coco", "needs outputs.labels: true"),
    ({"outputs": {"yolo": True, "labels": False}}, "outputs.yolo", "needs outputs.labels: true"),
    ({"outputs": {"mcap": 1}}, "outputs.mcap", "valid boolean"),
    ({"outputs": {"split": [0.5, 0.6, 0.1]}}, "outputs.split", "fractions must sum to 1, they sum to 1.2"),
    ({"outputs": {"split": [1.5, -0.5, 0.0]}}, "outputs.split", "fractions must be finite and >= 0"),
    ({"outputs": {"split": [0.5, 0.5]}}, "outputs.split.2", "Field required"),
    ({"outputs": {"split": [1.0, math.nan, 0.0]}}, "outputs.split.1", "finite number"),
    ({"targets": {"assets": [{"procedural": "urchin", "colour": "red"}]}}, "targets.assets.0.colour", "Extra inputs"),
    # unknown names
    ({"water": {"jerlov": ["II", "9Z"]}}, "water.jerlov", "unknown Jerlov type '9Z'"),
    ({"quality": "ultra"}, "quality", "'draft', 'fast', 'default' or 'high'"),
    ({"targets": {"assets": [{"procedural": "starfish"}]}}, "targets.assets.0.procedural", "'urchin'"),
    ({"terrain": {"styles": ["mud"]}}, "terrain.styles.0", "'sand', 'pebbles' or 'rock'"),
    # asset refs: exactly one source
    (
        {"targets": {"assets": [{"procedural": "urchin", "path": "u.obj"}]}},
        "targets.assets.0",
        "give exactly one of procedural, path, asset_id (got ['procedural', 'path'])",
    ),
    (
        {"distractors": {"assets": [{"procedural": "rock"}, {"variants": 3}]}},
        "distractors.assets.1",
        "give exactly one of procedural, path, asset_id (got none)",
    ),
    ({"terrain": {"mesh": {}}}, "terrain.mesh", "give exactly one of path, asset_id (got none)"),
    ({"terrain": {"texture": {"asset_id": "abc"}}}, "terrain.texture.asset_id", "should match pattern"),
    ({"targets": {"assets": []}}, "targets.assets", "at least 1 item"),
    # class names are one KITTI token
    ({"targets": {"class_name": "Sea Urchin"}}, "targets.class_name", "should match pattern"),
    ({"targets": {"class_name": "Urchin\t"}}, "targets.class_name", "should match pattern"),
    ({"targets": {"class_name": "Urchin\n"}}, "targets.class_name", "should match pattern"),
    ({"targets": {"class_name": ""}}, "targets.class_name", "should match pattern"),
    # one projection only
    (
        {"camera": {"hfov_deg": 60, "intrinsics": {"fx": 1, "fy": 1, "cx": 0, "cy": 0}}},
        "camera",
        "give either hfov_deg or intrinsics, not both",
    ),
    ({"water": {"jerlov": []}}, "water", "with no jerlov types, give absorption and scattering explicitly"),
    ({"water": {"model": "paper", "jerlov": []}}, "water", "with no jerlov types, give beta_D and B_inf explicitly"),
]


@pytest.mark.parametrize(("data", "path", "fragment"), REFUSED, ids=[f"{c[1]}-{i}" for i, c in enumerate(REFUSED)])
def test_invalid_value_is_refused_naming_the_field(data, path, fragment):
    (line,) = refusal(data)
    assert line.startswith(f"{path}: "), line
    assert fragment in line


def test_shard_size_over_the_shard_work_limit_is_refused_naming_shard_size():
    # 1920x1080 is 2.0736 megapixels: 289 frames are 599.3 (under 600), 290 are 601.3.
    ok = parse_spec({"shard_size": 289, "camera": {"width": 1920, "height": 1080}})
    assert ok.shard_size == 289
    (line,) = refusal({"shard_size": 290, "camera": {"width": 1920, "height": 1080}})
    assert "shard_size: 290 frames of 1920x1080 is 601 megapixels per shard, over the limit of 600" in line
    (line,) = refusal({"shard_size": 10_001})
    assert line.startswith("shard_size: ")


def test_every_bad_field_gets_its_own_line():
    lines = refusal({"frames": 0, "camera": {"width": 5000, "fov": 1}, "water": {"jerlov": ["X"]}}, source="s.yaml")
    assert sorted(line.split(": ", 1)[0] for line in lines) == ["camera.fov", "camera.width", "frames", "water.jerlov"]


def test_limits_themselves_are_valid():
    spec = parse_spec({"frames": MAX_FRAMES, "shard_size": 1, "camera": {"width": MAX_SIDE, "height": MAX_SIDE}})
    assert (spec.frames, spec.camera.width, spec.camera.height) == (MAX_FRAMES, MAX_SIDE, MAX_SIDE)
    counts = parse_spec({"targets": {"count": [0, MAX_OBJECTS]}, "distractors": {"count": [0, 0]}})
    assert (counts.targets.count, counts.distractors.count) == ((0, MAX_OBJECTS), (0, 0))


# Integer fields take integers only, boolean fields booleans only: a lax parse would read these as 1, 7, 2, True.
NOT_STRICT = [
    ("seed", True), ("seed", "7"), ("seed", 2.0), ("frames", 2.0), ("frames", "10"), ("shard_size", False),
    ("camera.width", 64.0), ("camera.height", "48"), ("targets.count", [1.0, 2]), ("terrain.cells", 16.0),
    ("targets.assets", [{"procedural": "urchin", "variants": 2.0}]), ("outputs.depth", 1), ("outputs.labels", "true"),
    ("outputs.range", 0.0), ("water.enabled", "no"),
    # Float fields take numbers only: a lax parse would read false as 0.0 and "12" as 12.0.
    ("noise.gaussian_sigma", False), ("camera.hfov_deg", True), ("lighting.sun_intensity", [True, 1.0]),
    ("terrain.size_m", "12"), ("outputs.split", [0.8, "0.1", 0.1]),
]


@pytest.mark.parametrize(("dotted", "value"), NOT_STRICT, ids=[f"{d}={v!r}" for d, v in NOT_STRICT])
def test_ints_and_bools_are_strict_naming_the_field(dotted, value):
    (line,) = refusal(apply_overrides({}, {dotted: value}))
    name = {"targets.count": "targets.count.0", "targets.assets": "targets.assets.0.variants",
            "lighting.sun_intensity": "lighting.sun_intensity.0", "outputs.split": "outputs.split.1"}.get(dotted, dotted)
    assert line.startswith(f"{name}: Input should be a valid "), line


@pytest.mark.parametrize(
    ("name", "text", "field"),
    [
        ("s.yaml", 'seed: "7"\n', "seed"),
        ("s.yaml", "frames: 2.0\n", "frames"),
        ("s.yaml", "outputs: {depth: 1}\n", "outputs.depth"),
        ("s.json", '{"camera": {"width": 64.0}}', "camera.width"),
        ("s.json", '{"shard_size": true}', "shard_size"),
    ],
)
def test_files_get_the_same_strict_types(tmp_path, name, text, field):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(SpecError) as info:
        load_spec(path)
    header, line = str(info.value).splitlines()
    assert header == f"{path}: invalid spec" and line.startswith(f"{field}: Input should be a valid "), line


def test_strict_fields_still_take_yaml_and_json_natives(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("seed: 7\nframes: 10\ncamera: {width: 64, height: 48}\noutputs: {depth: yes, meta: false}\n")
    spec = load_spec(path)
    got = (spec.seed, spec.frames, spec.camera.width, spec.outputs.depth, spec.outputs.meta)
    assert got == (7, 10, 64, True, False)
    # Float fields still take integers.
    assert parse_spec({"terrain": {"size_m": 3}}).terrain.size_m == 3.0


@pytest.mark.parametrize(
    ("dotted", "item", "limit"),
    [
        ("targets.assets", {"procedural": "urchin"}, MAX_ASSETS),
        ("distractors.assets", {"procedural": "rock"}, MAX_ASSETS),
        ("water.jerlov", "II", MAX_CHOICES),
        ("terrain.styles", "sand", MAX_CHOICES),
    ],
)
def test_lists_are_limited_naming_field_and_limit(dotted, item, limit):
    at_limit = parse_spec(apply_overrides({}, {dotted: [item] * limit}))
    section, field = dotted.split(".")
    assert len(getattr(getattr(at_limit, section), field)) == limit
    (line,) = refusal(apply_overrides({}, {dotted: [item] * (limit + 1)}))
    assert line == f"{dotted}: List should have at most {limit} items after validation, not {limit + 1}"


def test_non_mapping_spec_is_refused():
    with pytest.raises(SpecError) as info:
        parse_spec([1, 2], source="body")
    assert str(info.value) == "body: the spec must be a mapping, got list"


# --- spec files ------------------------------------------------------------------------------------------------

MAPPING = {
    "seed": 11,
    "frames": 5,
    "shard_size": 2,
    "quality": "draft",
    "camera": {"width": 64, "height": 48, "hfov_deg": 60.0, "clip": [0.05, 50.0]},
    "targets": {"class_name": "Urchin", "count": [1, 3], "assets": [{"procedural": "urchin", "variants": 2}]},
    "water": {"jerlov": ["I", "7C"], "beta_D": {"min": [0.1, 0.05, 0.02], "max": [0.4, 0.1, 0.05]}},
    "outputs": {"depth": True, "range": True},
}


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
    assert spec.targets.assets[1].asset_id == asset_id


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


# --- the CLI ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    """Run the CLI cases side by side (each start-up imports the worker): name -> (out, exit code, stdout, stderr)."""
    root = tmp_path_factory.mktemp("cli")
    bad_spec = root / "bad.yaml"
    bad_spec.write_text("camera:\n  width: 5000\n")
    full = root / "full"
    full.mkdir()
    (full / "keep.txt").write_text("mine")
    blocker = root / "a-file"
    blocker.write_text("")
    cases = {
        "bad_spec": ([str(bad_spec)], root / "out-bad"),
        "not_empty": ([str(EXAMPLE), "--width", "64", "--height", "48", "--frames", "1"], full),
        "unwritable": ([str(EXAMPLE), "--width", "64", "--height", "48", "--frames", "1"], blocker / "sub"),
    }
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-m", "service.cli", "generate", *args, "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=root,
        )
        for name, (args, out) in cases.items()
    }
    results = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=120)
        results[name] = (cases[name][1], proc.returncode, stdout, stderr)
    return results


def test_cli_invalid_spec_exits_2_naming_the_field_and_writes_nothing(cli_runs):
    out, code, stdout, stderr = cli_runs["bad_spec"]
    assert code == 2, stderr
    assert "\ncamera.width: " in stderr
    assert stdout == ""
    assert not out.exists()


def test_cli_refuses_a_non_empty_output_folder_with_exit_1(cli_runs):
    out, code, _, stderr = cli_runs["not_empty"]
    assert code == 1, stderr
    assert stderr.startswith(f"error: {out}: folder is not empty")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    assert (out / "keep.txt").read_text() == "mine"


def test_cli_refuses_an_unwritable_output_folder_with_exit_1(cli_runs):
    out, code, _, stderr = cli_runs["unwritable"]
    assert code == 1, stderr
    assert stderr.startswith(f"error: {out}: cannot create or list the output folder")
    assert not out.exists()


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
