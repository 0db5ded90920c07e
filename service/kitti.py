"""KITTI label_2 text parsing, for every reader of a dataset: export, preview, the API's preview route, tests."""

from __future__ import annotations

LABEL_FIELDS = 15


def parse_label_file(text: str) -> list[dict]:
    """Objects of a label_2 text, one dict per line with the keys type (str), truncated (float), occluded (int),
    alpha (float), bbox (4 floats, px), dimensions (h, w, l; m), location (x, y, z; m), rotation_y (float),
    and score (float) when the line has a 16th field."""
    objects = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split()
        if len(fields) not in (LABEL_FIELDS, LABEL_FIELDS + 1):
            raise ValueError(f"label line {number} has {len(fields)} fields, expected 15 or 16: {line!r}")
        try:
            values = [float(f) for f in fields[1:]]
            occluded = int(fields[2])
        except ValueError as error:
            raise ValueError(f"label line {number}: {error}") from None
        obj = {
            "type": fields[0],
            "truncated": values[0],
            "occluded": occluded,
            "alpha": values[2],
            "bbox": values[3:7],
            "dimensions": values[7:10],
            "location": values[10:13],
            "rotation_y": values[13],
        }
        if len(values) == LABEL_FIELDS:
            obj["score"] = values[14]
        objects.append(obj)
    return objects
