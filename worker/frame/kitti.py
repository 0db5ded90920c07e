"""Text of KITTI label_2 and calib files: formatting for the writer, parsing for tests and users' tools."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from seasynth.service.kitti import LABEL_FIELDS, parse_label_file  # noqa: F401 (parsing lives with the readers of both sides)
from seasynth.worker.frame.labels import KittiObject

# Calib matrices in file order and their shapes; P0..P3 are K [I | 0] for the single synthetic camera.
CALIB_SHAPES: dict[str, tuple[int, int]] = {
    "P0": (3, 4),
    "P1": (3, 4),
    "P2": (3, 4),
    "P3": (3, 4),
    "R0_rect": (3, 3),
    "Tr_velo_to_cam": (3, 4),
    "Tr_imu_to_velo": (3, 4),
}


def _fixed2(value: float) -> str:
    """value with exactly 2 decimals, never "-0.00"."""
    text = f"{value:.2f}"
    return "0.00" if text == "-0.00" else text


def format_label_line(obj: KittiObject) -> str:
    """The 15-field label_2 line of obj: numbers with 2 decimals, occluded as an integer."""
    numbers = (*obj.box2d, *obj.dims, *obj.location, obj.rotation_y)
    return " ".join([obj.type, _fixed2(obj.truncated), str(obj.occluded), _fixed2(obj.alpha), *map(_fixed2, numbers)])


def format_label_file(objs: Iterable[KittiObject]) -> str:
    """A frame's label_2 text: one line per object, each ending in a newline; "" when there are none."""
    return "".join(format_label_line(obj) + "\n" for obj in objs)


def format_calib(K: np.ndarray) -> str:
    """The seven-line calib text of one camera with intrinsics K (3, 3), pixels.

    Numbers use "%.12e" like the devkit's files (13 significant digits, so projections survive the round trip).
    """
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"K must be a finite (3, 3) matrix, got shape {K.shape}")
    projection = np.hstack([K, np.zeros((3, 1))])
    identity_34 = np.eye(3, 4)
    matrices = {
        "P0": projection,
        "P1": projection,
        "P2": projection,
        "P3": projection,
        "R0_rect": np.eye(3),
        "Tr_velo_to_cam": identity_34,
        "Tr_imu_to_velo": identity_34,
    }
    # Adding 0.0 turns -0.0 into 0.0 so no "-0.000000000000e+00" appears.
    lines = [f"{name}: " + " ".join(f"{v + 0.0:.12e}" for v in m.ravel()) for name, m in matrices.items()]
    return "\n".join(lines) + "\n"


def parse_calib(text: str) -> dict[str, np.ndarray]:
    """Matrices of a calib text by name: float64, (3, 4) for 12 numbers, (3, 3) for 9, else flat."""
    matrices = {}
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        name, colon, rest = line.partition(":")
        if not colon:
            raise ValueError(f"calib line {number} has no 'NAME:': {line!r}")
        try:
            values = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError as error:
            raise ValueError(f"calib line {number} ({name.strip()}): {error}") from None
        shape = {12: (3, 4), 9: (3, 3)}.get(values.size, (values.size,))
        matrices[name.strip()] = values.reshape(shape)
    return matrices
