"""The "up" direction of the surface a scene stands on (floor or table), from normals.

Distant light from below that surface's horizon cannot reach the scene directly; the light
estimate uses it to damp what the visible normals leave unconstrained (below-horizon
radiance). Found as the most common normal orientation among the surfaces that face up in
the image (against the camera's +y, which points down in OpenCV axes).
"""

from __future__ import annotations

import numpy as np

MIN_FACING_UP = 0.5  # cos of the largest tilt of a candidate normal from the image's "up"
CLUSTER_COS = np.cos(np.radians(15.0))  # normals within 15 degrees form the plane's cluster
MIN_FRACTION = 0.1  # the plane must hold this fraction of all known normals
_GRID = 20  # cells per side of the (x, z) histogram of candidate normals (~6 degrees)


def support_plane_up(normals_cam: np.ndarray, stride: int = 4) -> np.ndarray | None:
    """Unit normal (camera frame) of the dominant upward-facing plane, or None.

    normals_cam: (H, W, 3) unit normals pointing towards the camera side of the surface,
    zeros where unknown. Every `stride`-th pixel is used.
    """
    n = np.asarray(normals_cam, dtype=np.float64)[::stride, ::stride].reshape(-1, 3)
    n = n[np.any(n != 0.0, axis=1)]
    if len(n) == 0:
        return None
    candidates = n[-n[:, 1] > MIN_FACING_UP]
    if len(candidates) < MIN_FRACTION * len(n):
        return None
    # the most populated cell of a grid over (x, z): the candidates all lie on the cap y < 0
    cells = np.clip(((candidates[:, [0, 2]] + 1.0) * (_GRID / 2)).astype(np.int64), 0,
                    _GRID - 1)
    peak = np.argmax(np.bincount(cells[:, 0] * _GRID + cells[:, 1], minlength=_GRID ** 2))
    x, z = (np.array(divmod(peak, _GRID)) + 0.5) * (2.0 / _GRID) - 1.0
    centre = np.array([x, -np.sqrt(max(1.0 - x * x - z * z, 0.0)), z])
    centre /= np.linalg.norm(centre)
    cluster = candidates[candidates @ centre > CLUSTER_COS]
    if len(cluster) < MIN_FRACTION * len(n):
        return None
    up = cluster.mean(axis=0)
    return up / np.linalg.norm(up)
