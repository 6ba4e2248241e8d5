"""Which of the sampled pixels the light is fitted to: those near where the camera looks.

The light a virtual object receives is the light where it stands, and a view holds surfaces
lit otherwise: a room's far wall under a window's patch of sun, background lit by lamps
the objects never see. `near_look_at` keeps the sampled pixels within a radius (metres,
any direction) of the point the camera looks at, the median of the valid points within
LOOK_AT_DEG of the optical axis (docs/decisions/0063-fit-near-the-look-at-point.md).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from arlight.pipeline.transfer_upsampling import TransferSamples

LOOK_AT_DEG = 10.0  # half-angle of the cone about the optical axis whose points it takes
MIN_KEPT = 3000  # fewer samples within the radius: every sample is kept


def look_at_point(points_cam: np.ndarray) -> np.ndarray | None:
    """(3,) camera frame: the median of the valid points (z > 0) of `points_cam` (H, W, 3)
    within LOOK_AT_DEG of the optical axis (+z); of every valid point when none is; None
    without any valid point."""
    # over the image in place, one gather at the end: a quarter of the time of gathering
    # the valid points first, the same values (the same float32 sums as np.linalg.norm's)
    x, y, z = points_cam[..., 0], points_cam[..., 1], points_cam[..., 2]
    valid = z > 0.0
    cos = z / np.maximum(np.sqrt((x * x + y * y) + z * z), np.float32(1e-12))
    near = valid & (cos > math.cos(math.radians(LOOK_AT_DEG)))
    if np.any(near):
        return np.median(points_cam[near], axis=0).astype(np.float64)
    if not np.any(valid):
        return None
    return np.median(points_cam[valid], axis=0).astype(np.float64)


def near_look_at(
    samples: TransferSamples, points_cam: np.ndarray, radius_m: float
) -> TransferSamples:
    """The samples whose points (points_cam (H, W, 3), camera frame, metres) lie within
    `radius_m` of `look_at_point`; all of them when radius_m <= 0, when there is no look-at
    point or when fewer than MIN_KEPT would be left."""
    if radius_m <= 0.0 or not len(samples.pixel_v):
        return samples
    centre = look_at_point(points_cam)
    if centre is None:
        return samples
    p = points_cam[samples.pixel_v, samples.pixel_u].astype(np.float64)
    keep = np.flatnonzero(np.linalg.norm(p - centre, axis=1) < radius_m)
    if len(keep) < MIN_KEPT or len(keep) == len(samples.pixel_v):
        return samples
    return dataclasses.replace(
        samples,
        pixel_v=samples.pixel_v[keep],
        pixel_u=samples.pixel_u[keep],
        transfer=samples.transfer[keep],
        bounce=None if samples.bounce is None else samples.bounce[keep],
    )
