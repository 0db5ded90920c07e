"""The camera's view volume for culling: what GLRenderer skips drawing."""

from __future__ import annotations

import math

import numpy as np

from seasynth.worker.render import View


def sphere_in_view(view: View, centre_cam: np.ndarray, radius: float) -> bool:
    """Conservative frustum test of a bounding sphere (camera frame); False only if surely invisible."""
    x, y, z = centre_cam
    if z + radius < view.near or z - radius > view.far:
        return False
    fx, fy, cx, cy = view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2]
    planes = (
        (fx, 0.0, cx + 0.5),  # u >= -0.5
        (-fx, 0.0, view.width - 0.5 - cx),  # u <= w - 0.5
        (0.0, fy, cy + 0.5),
        (0.0, -fy, view.height - 0.5 - cy),
    )
    for a, b, c in planes:
        if (a * x + b * y + c * z) / math.sqrt(a * a + b * b + c * c) < -radius:
            return False
    return True
