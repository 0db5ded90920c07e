"""The dataset spec's refusals, each naming the field by its dotted path: values, limits, strict types."""

from __future__ import annotations

import math
import sys
import unicodedata

import pytest
from spec_helpers import refusal

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import MAX_FRAMES, apply_overrides, load_spec, parse_spec
from seasynth.service.spec.scene import MAX_ASSETS, MAX_OBJECTS, MAX_SIDE
from seasynth.service.spec.types import MAX_CHOICES
from seasynth.worker.frame.kitti import format_label_line, parse_label_file
from seasynth.worker.frame.labels import KittiObject

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
    # finite but beyond float32 or any scene: 1e40 overflows the renderer's float32 to inf, then NaN
    ({"lighting": {"sun_intensity": [1.0, 1e40]}}, "lighting.sun_intensity", "must lie within +-1,000,000"),
    ({"lighting": {"lamps": [{"intensity": [1e7, 1e7]}]}}, "lighting.lamps.0.intensity", "within +-1,000,000"),
    ({"lighting": {"lamps": [{"offset_m": [0.0, 1e300, 0.0]}]}}, "lighting.lamps.0.offset_m", "within +-1,000,000"),
    ({"targets": {"scale": [1.0, 101.0]}}, "targets.scale", "must lie within [0, 100]"),
    ({"distractors": {"scale": [1e300, 1e300]}}, "distractors.scale", "must lie within +-1,000,000"),
    ({"water": {"beta_jitter": [1.0, 1e3]}}, "water.beta_jitter", "must lie within [0, 100]"),
    ({"camera": {"look_at_jitter_m": 1e300}}, "camera.look_at_jitter_m", "less than or equal to 100"),
    ({"camera": {"clip": [0.02, 1e300]}}, "camera.clip", "must lie within +-1,000,000"),
    ({"camera": {"intrinsics": {"fx": 1e-300, "fy": 100, "cx": 0, "cy": 0}}}, "camera",
     "intrinsics.fx 1e-300 px gives a field of view of 170 deg or more over 640 px; at least 28"),
    ({"camera": {"width": 32, "height": 24, "intrinsics": {"fx": 100, "fy": 1.0, "cx": 0, "cy": 0}}}, "camera",
     "intrinsics.fy 1.0 px gives a field of view of 170 deg or more over 24 px; at least 1.05"),
    ({"camera": {"intrinsics": {"fx": 100, "fy": 100, "cx": 1e300, "cy": 0}}}, "camera.intrinsics.cx",
     "less than or equal to 1000000"),
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
    ({"targets": {"assets": [{"procedural": "kraken"}]}}, "targets.assets.0.procedural", "'urchin'"),
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
    # the forward-scatter blur spreads the physical model's scattered light
    ({"water": {"model": "paper", "forward_scatter": True}}, "water",
     "forward_scatter spreads light the physical model scatters; it needs water.enabled: true and water.model: "
     "physical (got enabled True, model paper)"),
    ({"water": {"enabled": False, "forward_scatter": True}}, "water", "(got enabled False, model physical)"),
    ({"water": {"forward_scatter": "yes"}}, "water.forward_scatter", "valid boolean"),
    ({"water": {"solved_column": 1}}, "water.solved_column", "valid boolean"),
]


@pytest.mark.parametrize(("data", "path", "fragment"), REFUSED, ids=[f"{c[1]}-{i}" for i, c in enumerate(REFUSED)])
def test_invalid_value_is_refused_naming_the_field(data, path, fragment):
    (line,) = refusal(data)
    assert line.startswith(f"{path}: "), line
    assert fragment in line


def test_class_names_the_kitti_writer_would_split_or_garble_are_refused_naming_the_field():
    # Every whitespace (str.isspace: what str.split() splits label lines on, U+001C..U+001F included, which the
    # pattern's \\S lets through) and every control character, inside a name.
    bad = [chr(c) for c in range(sys.maxunicode + 1)
           if chr(c).isspace() or unicodedata.category(chr(c)) == "Cc"]
    assert {"\x1c", "\x1d", "\x1e", "\x1f", "\x00", "\x7f", "\x85", "\u3000"} <= set(bad)
    for c in bad:
        (line,) = refusal({"targets": {"class_name": f"Sea{c}urchin"}})
        assert line.startswith("targets.class_name: "), (hex(ord(c)), line)
    for c in "\x1c\x1d\x1e\x1f\x00\x7f\x9b":  # the ones the pattern passes: named by code point
        (line,) = refusal({"targets": {"class_name": f"Sea{c}urchin"}})
        assert f"holds U+{ord(c):04X}, a whitespace or control character" in line
    # Names of other scripts and punctuation stay valid, and are one label field.
    for name in ("Seeigel_\u00e4", "\u30a6\u30cb", "sea-urchin/2", "a,b"):
        assert parse_spec({"targets": {"class_name": name}}).targets[0].class_name == name
        line = format_label_line(KittiObject(type=name, truncated=0.0, occluded=0, alpha=0.0, box2d=(0, 0, 1, 1),
                                             dims=(1, 1, 1), location=(0, 0, 1), rotation_y=0.0))
        assert [lab["type"] for lab in parse_label_file(line + "\n")] == [name]


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
    assert (counts.targets[0].count, counts.distractors.count) == ((0, MAX_OBJECTS), (0, 0))


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
    group = getattr(at_limit, section)
    assert len(getattr(group[0] if section == "targets" else group, field)) == limit
    (line,) = refusal(apply_overrides({}, {dotted: [item] * (limit + 1)}))
    assert line == f"{dotted}: List should have at most {limit} items after validation, not {limit + 1}"


def test_non_mapping_spec_is_refused():
    with pytest.raises(SpecError) as info:
        parse_spec([1, 2], source="body")
    assert str(info.value) == "body: the spec must be a mapping, got list"
