"""Which of the sampled pixels the light is fitted to: those near where the camera looks.

The light a virtual object receives is the light where it stands, and a view holds surfaces
lit otherwise: a room's far wall under a window's patch of sun, background lit by lamps
the objects never see. `near_look_at` keeps the sampled pixels within a radius (metres,
any direction) of the point the camera looks at, the median of the valid points within
LOOK_AT_DEG of the optical axis (docs/decisions/0063-fit-near-the-look-at-point.md).

Where the light is also fitted over the whole view (for the compact sources' search,
decision 0064), the two fits are estimates of one light from overlapping pixels: where
their directions agree the reported SH is their blend, `blended` with `whole_view_share`;
where they disagree (a closed room's walls lit otherwise than its floor) the fit near the
look-at point alone (docs/decisions/0067-the-two-fits-blended.md).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from arlight.pipeline.light_estimation import LightEstimate
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


def whole_view_share(disagreement_deg: float, share: float, fade_deg: float) -> float:
    """The whole view's share of the reported SH: `share` where the two fits' directions
    agree, falling linearly to 0 at `fade_deg` degrees between them (and beyond)."""
    return share * max(0.0, 1.0 - disagreement_deg / fade_deg)


def blended(near: LightEstimate, whole: LightEstimate, share: float) -> LightEstimate:
    """`near` with the bands both fits estimated of its SH (and RGB SH, where both have one)
    replaced by (1 - share) near + share whole; its other bands, confidence (bands_estimated
    included), residual and fit state stay the near fit's."""
    bands = min(near.confidence.bands_estimated, whole.confidence.bands_estimated)
    n = bands * bands

    def mix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = np.array(a, dtype=np.float64, copy=True)
        out[..., :n] = (1.0 - share) * a[..., :n] + share * b[..., :n]
        return out

    sh_rgb = near.sh_rgb
    if near.sh_rgb is not None and whole.sh_rgb is not None:
        sh_rgb = mix(near.sh_rgb, whole.sh_rgb)
    return dataclasses.replace(near, sh=mix(near.sh, whole.sh), sh_rgb=sh_rgb)
