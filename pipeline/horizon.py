"""The "up" direction of the surface a scene stands on (floor or table), from normals.

Distant light from below that surface's horizon cannot reach the scene directly: the radiance
transfer sees the lit ground there instead (`SupportPlane`), and the light estimate damps
what the visible normals leave unconstrained (below-horizon radiance). The plane's normal is
the most common orientation among the surfaces that face up in the image (against the
camera's +y, which points down in OpenCV axes), its offset the most common height.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arlight.pipeline.channels import any_nonzero

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
    n = n[any_nonzero(n)]
    if len(n) == 0:
        return None
    candidates = n[-n[:, 1] > MIN_FACING_UP]
    if len(candidates) < MIN_FRACTION * len(n):
        return None
    # the most populated cell of a grid over (x, z): the candidates all lie on the cap y < 0
    cells = np.clip(((candidates[:, [0, 2]] + 1.0) * (_GRID / 2)).astype(np.int64), 0, _GRID - 1)
    peak = np.argmax(np.bincount(cells[:, 0] * _GRID + cells[:, 1], minlength=_GRID**2))
    x, z = (np.array(divmod(peak, _GRID)) + 0.5) * (2.0 / _GRID) - 1.0
    centre = np.array([x, -np.sqrt(max(1.0 - x * x - z * z, 0.0)), z])
    centre /= np.linalg.norm(centre)
    cluster = candidates[candidates @ centre > CLUSTER_COS]
    if len(cluster) < MIN_FRACTION * len(n):
        return None
    up = cluster.mean(axis=0)
    return up / np.linalg.norm(up)


PLANE_TOLERANCE_M = 0.03  # a pixel lies on the plane within this (plus 1 % of its depth)
_HEIGHT_BIN_M = 0.01


@dataclass(frozen=True)
class SupportPlane:
    """The plane a scene stands on, camera frame: up . p + offset = 0 (metres).

    up: (3,) unit normal pointing to the side the camera sees (into the scene's space);
    offset: metres; on_plane: (H, W) bool, pixels lying on it (the visible ground).
    """

    up: np.ndarray
    offset: float
    on_plane: np.ndarray

    def height(self, points_cam: np.ndarray) -> np.ndarray:
        """Signed height (metres) of camera-frame points (..., 3) above the plane."""
        return np.asarray(points_cam, dtype=np.float64) @ self.up + self.offset


def support_plane(
    normals_cam: np.ndarray, points_cam: np.ndarray, stride: int = 4
) -> SupportPlane | None:
    """The dominant upward-facing plane (normal from `support_plane_up`, offset from the
    most common height of the pixels that face that way), or None.

    normals_cam: (H, W, 3) unit normals, zeros where unknown; points_cam: (H, W, 3) metres,
    camera frame, z = 0 where depth is missing.
    """
    up = support_plane_up(normals_cam, stride)
    if up is None:
        return None
    n, p = np.asarray(normals_cam), np.asarray(points_cam)
    facing = (n[::stride, ::stride] @ up > CLUSTER_COS) & (p[::stride, ::stride, 2] > 0)
    dist = p[::stride, ::stride][facing].astype(np.float64) @ up  # = -offset on the plane
    if len(dist) == 0:
        return None
    # the most common height (1 cm bins), refined by the median of the pixels near it:
    # the tops of objects face up too but hold fewer pixels than the ground
    bins = np.floor((dist - dist.min()) / _HEIGHT_BIN_M).astype(np.int64)
    peak = dist.min() + (np.argmax(np.bincount(bins)) + 0.5) * _HEIGHT_BIN_M
    near = dist[np.abs(dist - peak) < PLANE_TOLERANCE_M]
    offset = -float(np.median(near))
    # full resolution in the images' own precision (float32): no per-frame float64 copies
    up_n = up.astype(n.dtype)
    height = p @ up.astype(p.dtype) + np.asarray(offset, p.dtype)
    # the normal test matters: ground pixels whose (smoothed) normals tilt next to objects
    # are better off in segments of their own (a height-only mask: GT medians a 4 -> 22)
    on_plane = (
        (p[..., 2] > 0)
        & (np.abs(height) < PLANE_TOLERANCE_M + 0.01 * p[..., 2])
        & (n @ up_n > CLUSTER_COS)
    )
    return SupportPlane(up, offset, on_plane)
