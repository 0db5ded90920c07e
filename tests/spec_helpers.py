"""What the spec's tests share: the example spec, a spec mapping written to files, and the lines of a refusal."""

from __future__ import annotations

from pathlib import Path

import pytest

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import parse_spec

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "urchins.yaml"

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


def refusal(data, source="spec") -> list[str]:
    """The lines of the SpecError that parse_spec raises for `data` (the header line checked and dropped)."""
    with pytest.raises(SpecError) as info:
        parse_spec(data, source=source)
    header, *lines = str(info.value).splitlines()
    assert header == f"{source}: invalid spec"
    return lines
