"""One session's light-estimation pipeline: frames in, lighting out (DESIGN.md data flow).

Stages, named as the rows of the paper's table 1: Input, Reconstruct, Surface, DynGeo,
RadTransfer, LightEst (Rendering is skipped while there is no virtual scene to render).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager

import cv2
import numpy as np

from arlight.checks import CheckError, depth_metres
from arlight.pipeline import sh
from arlight.pipeline.camera import PinholeCamera
from arlight.pipeline.config import Config
from arlight.pipeline.depth_filter import filter_depth, intensity_from_rgb, normals_from_depth
from arlight.pipeline.frames import Confidence, FrameInput, FrameResult
from arlight.pipeline.horizon import SupportPlane, support_plane
from arlight.pipeline.light_estimation import (
    LUMA,
    LightEstimate,
    TemporalFilter,
    estimate_light,
    srgb_to_linear,
)
from arlight.pipeline.radiance_transfer import (
    AuxBufferArrays,
    compute_transfer,
    make_sampling_pattern,
    upsample_transfer,
)
from arlight.pipeline.segmentation import material_segments

log = logging.getLogger(__name__)

STAGES = ("Input", "Reconstruct", "Surface", "DynGeo", "RadTransfer", "LightEst", "Rendering")
MAX_DEPTH_M = 100.0  # larger (finite) depth values are treated as invalid sensor output


class FrameError(ValueError):
    """A frame that cannot be processed; the message names the field and the limit."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


def validate_frame(frame: FrameInput, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Checked colour (H, W, 3) uint8 and depth (H, W) float32 metres with NaN/inf/negative -> 0."""
    color = np.asarray(frame.color)
    depth = np.asarray(frame.depth)
    expected = (camera.height, camera.width)
    if color.ndim != 3 or color.shape[2] != 3:
        raise FrameError("color", f"expected shape (H, W, 3), got {color.shape}")
    if color.dtype != np.uint8:
        raise FrameError("color", f"expected dtype uint8, got {color.dtype}")
    if color.shape[:2] != expected:
        raise FrameError("color", f"size {color.shape[1]}x{color.shape[0]} does not match the "
                                  f"camera's {camera.width}x{camera.height}")
    if depth.ndim != 2:
        raise FrameError("depth", f"expected shape (H, W), got {depth.shape}")
    if depth.shape != expected:
        raise FrameError("depth", f"size {depth.shape[1]}x{depth.shape[0]} does not match the "
                                  f"colour image's {camera.width}x{camera.height}")
    try:
        depth = depth_metres(frame.depth, frame.depth_scale)
    except CheckError as exc:
        raise FrameError("depth", exc.message) from None
    if frame.pose is not None:
        pose = np.asarray(frame.pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise FrameError("pose", f"expected a finite 4x4 matrix, got shape {pose.shape}")
        r = pose[:3, :3]
        if np.abs(r.T @ r - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0:
            raise FrameError("pose", "rotation part is not a rotation (R^T R != I or det < 0)")
    if not np.isfinite(frame.timestamp):
        raise FrameError("timestamp", f"must be finite, got {frame.timestamp}")
    return color, depth


def smooth_depth_for_normals(depth_m: np.ndarray, window: int) -> np.ndarray:
    """Validity-weighted box mean of depth over `window` pixels, for normals only.

    One-pixel differences of sensor depth give normals that are mostly noise (Kinect noise at
    2-3 m is as large as the pixel footprint), and least squares on such normals explains
    albedo texture as shading. Pixels whose mean departs from their own depth by > 3 % (depth
    edges) are left out (0).
    """
    if window <= 1:
        return depth_m
    valid = (depth_m > 0).astype(np.float32)
    num = cv2.boxFilter(depth_m, -1, (window, window), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(valid, -1, (window, window), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    mean = np.where(den > 0, num / np.maximum(den, 1e-6), 0.0)
    keep = (depth_m > 0) & (np.abs(mean - depth_m) < 0.03 * depth_m)
    return np.where(keep, mean, 0.0).astype(np.float32)


class Pipeline:
    """Holds one session's state (volume, pose, temporal filter); see DESIGN.md.

    config: all parameters (Config.from_preset); camera: intrinsics of the (registered)
    colour and depth images; scene: virtual objects to render (not used yet: no
    differential rendering until a scene is given).
    """

    def __init__(self, config: Config, camera: PinholeCamera, scene=None):
        self.config = config
        self.camera = camera
        self.scene = scene
        self.pattern = make_sampling_pattern(config)
        self.filter = TemporalFilter(config.temporal_half_life_frames, config.change_reset_deg)
        self.frames_processed = 0
        self._volume = None
        if config.use_volume:
            from arlight.pipeline.reconstruction import VolumeReconstruction

            self._volume = VolumeReconstruction(config, camera)
        self._pose = np.eye(4)
        self._light_world: np.ndarray | None = None

    def process(self, frame: FrameInput) -> FrameResult:
        """Estimate the lighting of one frame. Raises FrameError on malformed input."""
        timings: dict[str, float] = {}
        diagnostics: dict = {}

        @contextmanager
        def stage(name: str):
            t0 = time.perf_counter()
            yield
            timings[name] = timings.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

        with stage("Input"):
            color, depth = validate_frame(frame, self.camera)
            intensity = intensity_from_rgb(color)
            color_linear = srgb_to_linear(color)

        aux_buffers = []
        depth_volume = None
        if self._volume is not None:
            surface = self._volume.process(color, depth, frame.pose, self._light_world)
            timings["Reconstruct"] = surface.timings_ms.get("Reconstruct", 0.0)
            timings["Surface"] = surface.timings_ms.get("Surface", 0.0)
            pose = surface.pose
            depth_volume = surface.depth_volume_m
            aux_buffers = surface.aux_buffers
            diagnostics["tracking_ok"] = bool(surface.tracking_ok)
        else:
            timings["Reconstruct"] = timings["Surface"] = 0.0
            pose = np.asarray(frame.pose, np.float64) if frame.pose is not None else self._pose
        self._pose = pose

        with stage("DynGeo"):
            depth_filtered, _ = filter_depth(depth, depth_volume, intensity, self.config)
            normals = normals_from_depth(
                smooth_depth_for_normals(depth_filtered, self.config.normal_window), self.camera)
            points = self.camera.unproject(depth_filtered)

            plane = None
            if (self.config.rt_horizon or self.config.horizon_prior > 0
                    or self.config.segment_split_ground):
                plane = support_plane(normals, points)

        with stage("RadTransfer"):
            aux = AuxBufferArrays.from_buffers(aux_buffers, pose) if aux_buffers else None
            luminance = color_linear @ LUMA.astype(np.float32) if self.config.rt_bounce else None
            transfer = compute_transfer(points, normals, self.camera, pose, self.pattern, aux,
                                        self.config, luminance,
                                        plane if self.config.rt_horizon else None)
            if self.config.rt_upsample and self.config.rt_subsample > 1:
                has_geometry = (depth_filtered > 0) & np.any(normals != 0, axis=2)
                transfer = upsample_transfer(transfer, has_geometry)

        with stage("LightEst"):
            up_world = pose[:3, :3] @ plane.up if plane is not None else None
            estimate = self._estimate(transfer, color_linear, depth_filtered, plane, up_world,
                                      below_horizon_unseen=self.config.rt_horizon)
            coeffs = self.filter.update(estimate.sh, estimate.confidence.value)
            direction_world, intensity_value = sh.dominant_light(coeffs)
            if np.any(direction_world):
                self._light_world = direction_world
        timings["Rendering"] = 0.0

        rotation = pose[:3, :3]
        self.frames_processed += 1
        diagnostics["residual_rel"] = estimate.residual_rel
        diagnostics["bounce_scale"] = estimate.bounce_scale
        diagnostics["horizon_prior_used"] = estimate.horizon_prior_used
        diagnostics["support_plane_up_world"] = (None if up_world is None
                                                 else [float(x) for x in up_world])
        diagnostics["raw_dominant_direction_world"] = sh.dominant_direction(estimate.sh).tolist()
        return FrameResult(
            timestamp=float(frame.timestamp), sh=coeffs, sh_camera=sh.rotate(coeffs, rotation.T),
            dominant_direction_world=direction_world,
            dominant_direction_camera=rotation.T @ direction_world,
            intensity=intensity_value, confidence=estimate.confidence, pose=pose.copy(),
            sh_rgb=estimate.sh_rgb, composite=None, timings_ms=timings, diagnostics=diagnostics)

    def _estimate(self, transfer, color_linear: np.ndarray, depth: np.ndarray,
                  plane: SupportPlane | None = None,
                  up_world: np.ndarray | None = None,
                  below_horizon_unseen: bool = False) -> LightEstimate:
        valid = transfer.valid
        n = self.config.sh_bands ** 2
        if not np.any(valid):
            return LightEstimate(np.zeros(n), Confidence(reason="no valid depth"),
                                 np.zeros((3, n)) if self.config.estimate_rgb else None)
        grid = np.ix_(transfer.pixel_v, transfer.pixel_u)
        colors = color_linear[grid][valid]
        segments = None
        if self.config.albedo_segments:
            segments = material_segments(
                color_linear, depth, features=self.config.segment_features,
                illuminant_weight=self.config.segment_illuminant_weight)
            if plane is not None and self.config.segment_split_ground:
                # what stands on the ground is rarely made of the ground's material
                segments = segments * 2 + plane.on_plane
            segments = segments[grid][valid]
        bounce = transfer.bounce[valid] if transfer.bounce is not None else None
        return estimate_light(transfer.transfer[valid], colors, self.config, segments, bounce,
                              up_world, below_horizon_unseen)
