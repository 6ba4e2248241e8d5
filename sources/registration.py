"""Depth from a separate depth camera, reprojected into the colour camera.

Some data sets (7-Scenes) store depth as the depth camera saw it, beside colour from another
camera a few centimetres away. `register_depth` moves every depth pixel into the colour
camera; `DepthRegistration` does it for a reader and quantises the result again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.checks import depth_metres
from arlight.pipeline.splat import splat_nearest
from arlight.sources.depth_encodings import metres_to_units


def register_depth(
    depth_m: np.ndarray,
    depth_camera: PinholeCamera,
    color_camera: PinholeCamera,
    color_from_depth: np.ndarray,
) -> np.ndarray:
    """Depth (H_c, W_c) float32 metres in the colour camera from depth (H_d, W_d) metres.

    Each valid depth pixel is unprojected with depth_camera, moved by color_from_depth (4x4)
    and splatted to its nearest colour pixel; where several land, the nearest surface wins.
    Colour pixels nothing lands on are 0 (missing).
    """
    h, w = color_camera.height, color_camera.width
    valid = np.isfinite(depth_m) & (depth_m > 0)
    if not valid.any():
        return np.zeros((h, w), np.float32)
    rows, cols = np.nonzero(valid)
    z_d = depth_m[valid].astype(np.float64)
    x_d = (cols - depth_camera.cx) / depth_camera.fx * z_d
    y_d = (rows - depth_camera.cy) / depth_camera.fy * z_d
    # written out per component: (N, 3) @ (3, 3) through BLAS is slower by 10x here
    m = np.asarray(color_from_depth, dtype=np.float64)
    x = m[0, 0] * x_d + m[0, 1] * y_d + m[0, 2] * z_d + m[0, 3]
    y = m[1, 0] * x_d + m[1, 1] * y_d + m[1, 2] * z_d + m[1, 3]
    z = m[2, 0] * x_d + m[2, 1] * y_d + m[2, 2] * z_d + m[2, 3]
    with np.errstate(divide="ignore", invalid="ignore"):  # z <= 0 is dropped by the splat
        u = color_camera.fx * x / z + color_camera.cx
        v = color_camera.fy * y / z + color_camera.cy
    return splat_nearest(u, v, z, w, h)  # the nearest surface wins


@dataclass(frozen=True)
class DepthRegistration:
    """Reproject a reader's depth from `depth_camera` into the colour camera.

    color_from_depth: (4, 4) metres, depth camera -> colour camera. depth_scale: units per
    metre of the registered uint16 depth (the reprojected z are no longer the stored integers).
    """

    depth_camera: PinholeCamera
    color_from_depth: np.ndarray
    depth_scale: float

    def __call__(
        self, units: np.ndarray, units_per_metre: float, color_camera: PinholeCamera
    ) -> np.ndarray:
        """(H_c, W_c) uint16 at self.depth_scale from the depth camera's uint16 `units`."""
        depth_m = depth_metres(units, units_per_metre)
        registered = register_depth(depth_m, self.depth_camera, color_camera, self.color_from_depth)
        return metres_to_units(registered, self.depth_scale)
