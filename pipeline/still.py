"""A camera held still: when the work of the last frame may serve this one.

A tablet held over a table barely moves for seconds at a time. What depends only on the
camera's pose and the static scene (the volume's ray cast, the auxiliary buffers, the
fusion of yet another view of the same surfaces) then changes by less than its own noise,
and what depends on the pose and the depth image (the filtered geometry and the radiance
transfer) changes only where something in the view moved. The light estimate itself always
runs on the new colour image, so a change of the light is followed at once.

`StillCamera` makes the decision for one such piece of work: reuse while the pose stays
within `ReuseParams.still_translation_m` and `still_rotation_deg` of the pose the work was
last done at, (optionally) while the depth image stays within `still_depth_change` of the
depth it was done on, and for at most `still_reuse_frames` frames in a row (then it is done
again; 0 turns reuse off). Poses are world_from_cam 4x4 (metres); depth (H, W) metres,
0 = missing.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from arlight.pipeline.config import ReuseParams

DEPTH_BLOCK_PX = 8  # depth is compared as means over blocks of this many pixels per side
# a block has changed when its mean depth moved by more than this (metres + relative)
DEPTH_TOLERANCE_M = 0.02
DEPTH_TOLERANCE_REL = 0.02


def pose_change(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation degrees) between two world_from_cam poses."""
    translation = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    cos = (float(np.trace(a[:3, :3].T @ b[:3, :3])) - 1.0) * 0.5
    return translation, math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def block_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H/8, W/8) float32 mean of the valid depth in each DEPTH_BLOCK_PX block (0: none)."""
    depth = np.asarray(depth_m, np.float32)
    h, w = depth.shape
    size = (max(1, w // DEPTH_BLOCK_PX), max(1, h // DEPTH_BLOCK_PX))
    valid = (depth > 0).astype(np.float32)
    total = cv2.resize(depth, size, interpolation=cv2.INTER_AREA)
    share = cv2.resize(valid, size, interpolation=cv2.INTER_AREA)
    return np.where(share > 0.5, total / np.maximum(share, 1e-6), 0.0).astype(np.float32)


def depth_change(before: np.ndarray, after: np.ndarray) -> float:
    """Share (0..1) of the blocks with depth in either image (`block_depth`) whose depth
    appeared, vanished or moved by more than the tolerance."""
    seen = (before > 0) | (after > 0)
    if not np.any(seen):
        return 0.0
    moved = np.abs(after - before) > DEPTH_TOLERANCE_M + DEPTH_TOLERANCE_REL * before
    changed = seen & (((before > 0) != (after > 0)) | moved)
    return float(np.count_nonzero(changed)) / float(np.count_nonzero(seen))


class StillCamera:
    """Whether one piece of work may be reused for this frame (module docstring).

    params: the reuse thresholds; with_depth: also require the depth image to be unchanged
    (for work that reads the depth, not only the pose). Call `may_reuse` once per frame;
    when it says no, do the work and call `did_work` with that frame's pose (and depth).
    """

    def __init__(self, params: ReuseParams, with_depth: bool = False):
        self.params = params
        self.with_depth = with_depth
        self._pose: np.ndarray | None = None
        self._depth: np.ndarray | None = None
        self.reused_in_a_row = 0
        self.reused_total = 0

    def may_reuse(self, pose: np.ndarray, depth_m: np.ndarray | None = None) -> bool:
        """True when this frame may take the last result (and counts it as reused)."""
        p = self.params
        if self._pose is None or self.reused_in_a_row >= p.still_reuse_frames:
            return False
        translation, rotation = pose_change(self._pose, pose)
        if translation > p.still_translation_m or rotation > p.still_rotation_deg:
            return False
        if self.with_depth:
            if depth_m is None or self._depth is None:
                return False
            if depth_change(self._depth, block_depth(depth_m)) > p.still_depth_change:
                return False
        self.reused_in_a_row += 1
        self.reused_total += 1
        return True

    def did_work(self, pose: np.ndarray, depth_m: np.ndarray | None = None) -> None:
        """The work was done for this pose (and depth): the next frames compare with it."""
        self._pose = np.array(pose, np.float64, copy=True)
        self._depth = None if depth_m is None or not self.with_depth else block_depth(depth_m)
        self.reused_in_a_row = 0

    def reset(self) -> None:
        self._pose = self._depth = None
        self.reused_in_a_row = 0
