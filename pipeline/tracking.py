"""Frame-to-model tracking (section 4 of seeds/000): projective point-to-plane ICP, coarse
to fine over 3 pyramid levels (Open3D's multi-scale RGB-D odometry, tensor API), of the
current depth against the previous frame's D_v (the model).

A frame that cannot be tracked is reported with the reason (`TrackingResult.reason`), never
swallowed. Open3D's odometry sums its normal equations with a TBB parallel reduction: poses
are reproducible only with Open3D on one thread, which an entry point may choose once
(`arlight --open3d-threads 1`, `arlight.pipeline.runtime.configure_open3d_threads`); the
default (all cores) leaves run-to-run pose differences of ~1e-5 m.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from arlight.core.camera import PinholeCamera

TRACKING_ITERATIONS = (6, 3, 1)  # Open3D's t.pipelines.slam defaults
# fewer ICP inliers than this fraction of the valid input depth pixels: failure (a good
# frame has 0.8-1; a 30 cm / 6 degree jump of 7-Scenes frames that ICP cannot bridge, 0.2)
TRACKING_MIN_INLIER_FRACTION = 0.3
TRACKING_MAX_STEP_M = 0.3  # a larger jump between consecutive frames is a failure
TRACKING_MAX_STEP_RAD = np.deg2rad(30.0)
TRACKING_MIN_VALID_PIXELS = 100  # fewer valid depth pixels (input or model): not tracked


@dataclass(frozen=True)
class TrackingResult:
    """prev_from_cur: (4, 4) motion of the camera since the model's frame (None unless ok);
    reason: why the frame was not tracked ("" when ok); inlier_fraction: ICP inliers per
    valid input depth pixel (NaN where ICP did not run)."""

    ok: bool
    prev_from_cur: np.ndarray | None = None
    reason: str = ""
    inlier_fraction: float = float("nan")

    def to_dict(self) -> dict:
        """Plain JSON types, for FrameResult.diagnostics."""
        out: dict = {"ok": bool(self.ok), "reason": self.reason}
        if math.isfinite(self.inlier_fraction):
            out["inlier_fraction"] = float(self.inlier_fraction)
        return out


MAX_REASON_CHARS = 300  # a reason travels in Result.diagnostics (strings <= 1024 there)


def _open3d_message(exc: Exception) -> str:
    """Open3D's error text without its terminal colours and C++ source location, bounded."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).strip()
    text = re.sub(r"^\[Open3D Error\] \(.*?\) \S+:\d+: ", "", text, flags=re.S)
    return text if len(text) <= MAX_REASON_CHARS else text[: MAX_REASON_CHARS - 3] + "..."


def _rotation_angle(rot: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))


class FrameToModelTracker:
    """Point-to-plane ICP of a depth image against a model depth image of the same camera.

    depth_max_m: depth beyond this is not used; depth_diff_m: correspondence gate (Open3D's
    depth_outlier_trunc; its Huber delta is 5/7 of it, Open3D's 7 cm : 5 cm).
    """

    def __init__(
        self, camera: PinholeCamera, device: o3c.Device, depth_max_m: float, depth_diff_m: float
    ):
        self.camera = camera
        self.depth_max_m = depth_max_m
        self._intrinsic = o3c.Tensor(camera.matrix, o3c.float64)
        self._no_color = o3d.t.geometry.Image(
            o3c.Tensor.zeros((camera.height, camera.width, 1), o3c.uint8, device)
        )
        self._criteria = [
            o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in TRACKING_ITERATIONS
        ]
        self._loss = o3d.t.pipelines.odometry.OdometryLossParams(
            depth_outlier_trunc=depth_diff_m, depth_huber_delta=depth_diff_m * 5.0 / 7.0
        )

    def track(
        self, depth_image: o3d.t.geometry.Image, n_valid: int, model_depth: o3c.Tensor | None
    ) -> TrackingResult:
        """Motion from the model's frame to the current one, or why there is none.

        depth_image: current depth (metres, 0 = missing) with n_valid valid pixels;
        model_depth: (H, W) D_v of the previous frame on the device, None if there is none.
        """
        if model_depth is None:
            return TrackingResult(False, reason="no model to track against (V not cast yet)")
        if n_valid < TRACKING_MIN_VALID_PIXELS:
            return TrackingResult(
                False,
                reason=f"too little depth: {n_valid} valid pixels < {TRACKING_MIN_VALID_PIXELS}",
            )
        n_model = int((model_depth > 0).to(o3c.int64).sum().item())
        if n_model < TRACKING_MIN_VALID_PIXELS:
            return TrackingResult(
                False,
                reason=f"too little model depth (D_v): {n_model} "
                f"pixels < {TRACKING_MIN_VALID_PIXELS}",
            )
        odometry = o3d.t.pipelines.odometry
        try:
            # point-to-plane odometry reads depth only; the colour slot holds a placeholder
            result = odometry.rgbd_odometry_multi_scale(
                o3d.t.geometry.RGBDImage(self._no_color, depth_image),
                o3d.t.geometry.RGBDImage(self._no_color, o3d.t.geometry.Image(model_depth)),
                self._intrinsic,
                o3c.Tensor(np.eye(4)),
                1.0,
                self.depth_max_m,
                self._criteria,
                odometry.Method.PointToPlane,
                self._loss,
            )
        except RuntimeError as exc:  # Open3D raises when ICP finds no correspondences
            return TrackingResult(False, reason=f"ICP failed: {_open3d_message(exc)}")
        prev_from_cur = result.transformation.numpy()
        # Open3D's fitness is inliers per image pixel; relate it to the pixels with depth
        inliers = result.fitness * self.camera.width * self.camera.height / n_valid
        reason = self._implausible(prev_from_cur, inliers)
        if reason:
            return TrackingResult(False, reason=reason, inlier_fraction=inliers)
        return TrackingResult(True, prev_from_cur, inlier_fraction=inliers)

    @staticmethod
    def _implausible(prev_from_cur: np.ndarray, inlier_fraction: float) -> str:
        """Why an ICP result is not trusted ("" when it is)."""
        if not np.all(np.isfinite(prev_from_cur)):
            return "ICP gave a non-finite pose"
        if inlier_fraction < TRACKING_MIN_INLIER_FRACTION:
            return (
                f"too few ICP inliers: {inlier_fraction:.2f} of the valid depth < "
                f"{TRACKING_MIN_INLIER_FRACTION}"
            )
        step_m = float(np.linalg.norm(prev_from_cur[:3, 3]))
        if step_m > TRACKING_MAX_STEP_M:
            return f"implausible jump: {step_m:.2f} m > {TRACKING_MAX_STEP_M} m"
        angle = _rotation_angle(prev_from_cur[:3, :3])
        if angle > TRACKING_MAX_STEP_RAD:
            return (
                f"implausible jump: {math.degrees(angle):.1f} deg > "
                f"{math.degrees(TRACKING_MAX_STEP_RAD):.0f} deg"
            )
        return ""
