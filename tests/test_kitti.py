"""Tests of seasynth.worker.frame.kitti: label_2 and calib text, and their parsers."""

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.shards import frame_name
from seasynth.service.spec.dataset import MAX_FRAMES
from seasynth.worker.frame.kitti import (
    CALIB_SHAPES,
    format_calib,
    format_label_file,
    format_label_line,
    parse_calib,
    parse_label_file,
)
from seasynth.worker.frame.labels import KittiObject

TWO_DECIMALS = re.compile(r"-?\d+\.\d{2}")
K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])


def urchin(**changes):
    fields = dict(
        type="Urchin",
        truncated=0.25,
        occluded=1,
        alpha=-1.234,
        box2d=(10.0, 20.0, 110.0, 95.0),
        dims=(0.05, 0.11, 0.12),
        location=(0.4, 1.2, 3.5),
        rotation_y=-0.8,
    )
    return KittiObject(**(fields | changes))


def assert_line_format(line):
    fields = line.split(" ")
    assert len(fields) == 15
    assert re.fullmatch(r"\S+", fields[0])
    assert fields[2] in {"0", "1", "2", "3"}
    for field in fields[1:2] + fields[3:]:
        assert TWO_DECIMALS.fullmatch(field), field
        assert field != "-0.00"


def test_label_line_fields():
    line = format_label_line(urchin())
    assert line == "Urchin 0.25 1 -1.23 10.00 20.00 110.00 95.00 0.05 0.11 0.12 0.40 1.20 3.50 -0.80"
    assert_line_format(line)


def test_negative_zero_never_appears():
    obj = urchin(alpha=-0.0, rotation_y=-0.004, location=(-0.001, -0.0, 2.0), truncated=-0.0)
    line = format_label_line(obj)
    assert "-0.00" not in line
    assert line.split()[3] == "0.00" and line.split()[11] == "0.00" and line.split()[14] == "0.00"
    assert format_label_line(urchin(rotation_y=-0.005)).split()[14] == "-0.01"  # true negatives keep their sign


def test_label_file_layout():
    objs = [urchin(), urchin(type="Rock", occluded=0)]
    text = format_label_file(objs)
    assert text == format_label_line(objs[0]) + "\n" + format_label_line(objs[1]) + "\n"
    assert format_label_file([]) == ""
    assert format_label_file(iter(objs)) == text


finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@settings(deadline=None, max_examples=200)
@given(
    st.lists(
        st.builds(
            KittiObject,
            type=st.from_regex(r"[A-Za-z_][A-Za-z0-9_\-]{0,11}", fullmatch=True),
            truncated=st.floats(0.0, 1.0),
            occluded=st.integers(0, 3),
            alpha=st.floats(-np.pi, np.pi),
            box2d=st.tuples(finite, finite, finite, finite),
            dims=st.tuples(finite, finite, finite),
            location=st.tuples(finite, finite, finite),
            rotation_y=st.floats(-np.pi, np.pi),
        ),
        max_size=5,
    )
)
def test_label_file_round_trip(objs):
    text = format_label_file(objs)
    for line in text.splitlines():
        assert_line_format(line)
    parsed = parse_label_file(text)
    assert len(parsed) == len(objs)
    for obj, back in zip(objs, parsed):
        assert back["type"] == obj.type and back["occluded"] == obj.occluded
        expected = [obj.truncated, obj.alpha, *obj.box2d, *obj.dims, *obj.location, obj.rotation_y]
        got = [back["truncated"], back["alpha"], *back["bbox"], *back["dimensions"], *back["location"]]
        got.append(back["rotation_y"])
        np.testing.assert_allclose(got, expected, rtol=0, atol=0.005 + 1e-9)
        assert "score" not in back


def test_parse_label_file_reads_scores_and_rejects_bad_lines():
    line = format_label_line(urchin()) + " 0.87"
    assert parse_label_file(line)[0]["score"] == 0.87
    assert parse_label_file("") == []
    with pytest.raises(ValueError, match="line 2"):
        parse_label_file(format_label_line(urchin()) + "\nUrchin 0.00 0\n")
    with pytest.raises(ValueError, match="line 1"):
        parse_label_file(format_label_line(urchin()).replace(" 1 ", " x ", 1))


def test_calib_layout():
    text = format_calib(K)
    assert text.endswith("\n") and not text.endswith("\n\n")
    lines = text.splitlines()
    assert [line.split(":")[0] for line in lines] == list(CALIB_SHAPES)
    for line, shape in zip(lines, CALIB_SHAPES.values()):
        numbers = line.split(": ", 1)[1].split(" ")
        assert len(numbers) == np.prod(shape)
        assert all(re.fullmatch(r"-?\d\.\d{12}e[+-]\d{2,3}", n) for n in numbers), line
    assert "-0.000000000000e+00" not in format_calib(K * -0.0 + np.eye(3))


def test_calib_round_trip():
    calib = parse_calib(format_calib(K))
    assert set(calib) == set(CALIB_SHAPES)
    expected = np.hstack([K, np.zeros((3, 1))])
    for name in ("P0", "P1", "P2", "P3"):
        assert calib[name].shape == (3, 4)
        np.testing.assert_allclose(calib[name], expected, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(calib["R0_rect"], np.eye(3))
    np.testing.assert_array_equal(calib["Tr_velo_to_cam"], np.eye(3, 4))
    np.testing.assert_array_equal(calib["Tr_imu_to_velo"], np.eye(3, 4))


def test_calib_keeps_awkward_intrinsics():
    odd = np.array([[1234.56789012345, 0.25, 640.123456789], [0.0, 1230.987654321, 359.5], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(parse_calib(format_calib(odd))["P2"][:, :3], odd, rtol=1e-12, atol=0)


def test_calib_rejects_bad_input():
    with pytest.raises(ValueError, match="K"):
        format_calib(np.eye(4))
    with pytest.raises(ValueError, match="line 1"):
        parse_calib("P0 1 2 3")
    with pytest.raises(ValueError, match="P1"):
        parse_calib("P1: 1 2 x")


def test_every_frame_of_the_largest_dataset_has_a_six_digit_name():
    assert (frame_name(0), frame_name(MAX_FRAMES - 1)) == ("000000", "999999")
    with pytest.raises(ValueError, match=r"outside 0\.\.999999"):
        frame_name(MAX_FRAMES)
    with pytest.raises(ValueError):
        frame_name(-1)
