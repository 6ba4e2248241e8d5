"""Z-buffer splatting: points that land on the same pixel keep the nearest depth."""

from __future__ import annotations

import numpy as np


def splat_nearest(
    u: np.ndarray,
    v: np.ndarray,
    z: np.ndarray,
    width: int,
    height: int,
    max_depth_m: float = np.inf,
) -> np.ndarray:
    """(height, width) float32 depth image, metres, 0 = nothing landed.

    u, v: (N,) pixel coordinates (rounded to the nearest pixel centre here); z: (N,) depth in
    metres. Points outside the image or with z not in (0, max_depth_m] are dropped; where
    several land on one pixel, the smallest z wins.
    """
    u = np.rint(u)
    v = np.rint(v)
    keep = (u >= 0) & (u < width) & (v >= 0) & (v < height) & (z > 0) & (z <= max_depth_m)
    flat = v[keep].astype(np.int64) * width + u[keep].astype(np.int64)
    zbuf = np.full(height * width, np.inf)
    np.minimum.at(zbuf, flat, z[keep])
    zbuf[~np.isfinite(zbuf)] = 0.0
    return zbuf.reshape(height, width).astype(np.float32)
