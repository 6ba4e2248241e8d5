"""Reconstruct and Surface stages: the volume V, G_v = (D_v, N_v) and the auxiliary buffers.

Section 4 of the image-space illumination paper (seeds/000): the static scene is fused into a
TSDF volume V (`volume.TsdfVolume`), the camera is tracked frame-to-model against V
(`tracking.FrameToModelTracker`), and V is ray-cast into the current view to give the
geometry buffer ``G_v = (D_v, N_v)``. Section 5.1 adds orthographic geometry buffers
extracted from V (`aux_buffers`). `VolumeReconstruction` runs them in that order, once per
frame; the Open3D 0.20 behaviours they correct are listed in volume.py.

Frames and units: metres; camera axes are OpenCV (x right, y down, z forward); poses are
``world_from_cam`` (camera-to-world) 4x4 float64. The world frame is the first frame's camera
frame unless poses are supplied.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import open3d.core as o3c

from arlight.core.camera import PinholeCamera
from arlight.core.checks import CheckError, check_image, check_rigid
from arlight.pipeline.aux_buffers import AuxBufferRenderer, OrthoBuffer
from arlight.pipeline.config import AuxBufferParams, Config, ReuseParams, VolumeParams
from arlight.pipeline.still import StillCamera
from arlight.pipeline.tracking import FrameToModelTracker, TrackingResult
from arlight.pipeline.volume import TsdfVolume


@dataclass
class SurfaceOutput:
    """Per-frame output of the Reconstruct and Surface stages.

    pose: (4, 4) float64 world_from_cam used for this frame.
    depth_volume_m: (H, W) float32, D_v: V ray-cast into the current view, metres along the
        optical axis, 0 = no surface.
    normals_volume: (H, W, 3) float32, N_v: unit outward surface normals of V in the CAMERA
        frame (pointing towards the free side), zeros where D_v is 0.
    aux_buffers: the auxiliary orthographic buffers (empty if disabled or V is not used).
    tracking_ok: False when the frame could not be tracked (the previous pose was kept and the
        frame was not fused into V); tracking says why (`TrackingResult.reason`).
    timings_ms: {"Reconstruct": track + integrate, "Surface": ray cast + aux buffers}.
    reused: True when the camera was held still (ReuseParams): the frame was tracked but
        not fused, and D_v, N_v and the aux buffers are those of the last frame that was.
    """

    pose: np.ndarray
    depth_volume_m: np.ndarray
    normals_volume: np.ndarray
    aux_buffers: list[OrthoBuffer]
    tracking_ok: bool
    timings_ms: dict[str, float] = field(default_factory=dict)
    tracking: TrackingResult = field(default_factory=lambda: TrackingResult(True))
    reused: bool = False


# the Surface cast is sub-sampled only while it keeps at least this many columns: the size
# it was measured at (640x480 sequences cast at 320x240); smaller images are cast whole (at
# 80x60, casting 40x30 cost the light estimate 40 % of its usable pixels)
SURFACE_MIN_CAST_WIDTH = 320


def surface_subsample(params: VolumeParams, camera: PinholeCamera) -> int:
    """The sub-sampling of the Surface ray cast for this camera: params.surface_subsample,
    lowered so that the cast keeps SURFACE_MIN_CAST_WIDTH columns (1 below that)."""
    return max(1, min(params.surface_subsample, camera.width // SURFACE_MIN_CAST_WIDTH))


class VolumeReconstruction:
    """One session's volume V: tracking, TSDF fusion, ray casting and auxiliary buffers.

    volume, aux: the stages' parameters (see TsdfVolume for the volume's); camera:
    intrinsics of the depth images (registered to colour); device: Open3D device of V;
    reuse: when a still camera's frames skip fusion and casting (None: never).
    `from_config` takes them from a Config.

    One instance per session; not safe to call from several threads at once.
    """

    def __init__(
        self,
        volume: VolumeParams,
        aux: AuxBufferParams,
        camera: PinholeCamera,
        device: str = "CPU:0",
        reuse: ReuseParams | None = None,
    ):
        self.params = volume
        self.aux_params = aux
        self.camera = camera
        self.device = o3c.Device(device)
        if self.device.get_type() == o3c.Device.DeviceType.CUDA and not o3c.cuda.is_available():
            raise RuntimeError(
                f"device is {device!r} but this Open3D build has no CUDA device; "
                "use device='CPU:0' (--set device=CPU:0)"
            )
        self._tracker = FrameToModelTracker(
            camera, self.device, volume.depth_max_m, volume.tracking_depth_diff_m
        )
        self._volume = TsdfVolume(volume, camera, self.device)
        self._aux = AuxBufferRenderer(aux)
        self._still = StillCamera(reuse or ReuseParams(still_reuse_frames=0))
        self.reset()

    @classmethod
    def from_config(cls, config: Config, camera: PinholeCamera) -> VolumeReconstruction:
        return cls(config.volume, config.aux, camera, config.device, config.reuse)

    def reset(self) -> None:
        """Forget the volume, the pose and the cached buffers (a new session)."""
        self._volume.reset()
        self._aux.reset()
        self.pose = np.eye(4)  # world_from_cam of the latest frame
        self.frame_index = 0  # frames processed
        self._model_depth: o3c.Tensor | None = None  # D_v of the previous frame, on device
        self._last: SurfaceOutput | None = None  # of the last frame fused and cast
        self._still.reset()

    @property
    def voxel_grid(self) -> o3d.t.geometry.VoxelBlockGrid:
        """The TSDF volume V ("tsdf" and "weight" per voxel), e.g. to export a mesh."""
        return self._volume.voxel_grid

    @property
    def num_blocks(self) -> int:
        """Voxel blocks allocated in V so far (memory: block_resolution^3 * 8 bytes each)."""
        return self._volume.num_blocks

    @property
    def frames_integrated(self) -> int:
        return self._volume.frames_integrated

    def surface_points(self, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Zero crossings of V (`TsdfVolume.surface_points`)."""
        return self._volume.surface_points(stride)

    def triangle_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """V as a world-frame triangle mesh (`TsdfVolume.triangle_mesh`)."""
        return self._volume.triangle_mesh()

    # ---------------------------------------------------------------- per frame
    def process(
        self,
        color_rgb_u8: np.ndarray,
        depth_m: np.ndarray,
        pose: np.ndarray | None,
        light_direction_world: np.ndarray | None = None,
    ) -> SurfaceOutput:
        """Track (unless pose is given), fuse the frame into V, ray-cast G_v and aux buffers.

        The checked entry for library use (the Pipeline validates its frames once and calls
        `process_validated`). color_rgb_u8: (H, W, 3) uint8 RGB (checked; only depth is
        fused into V). depth_m: (H, W) float metres along the optical axis, 0 or NaN =
        missing. pose: (4, 4) rigid world_from_cam, or None to track frame-to-model against
        the previous frame's D_v. light_direction_world: finite non-zero vector towards the
        dominant light, or None (no "light" buffer). Raises arlight.core.checks.CheckError
        (a ValueError) naming the argument.
        """
        cam = self.camera
        size = (cam.width, cam.height)
        check_image(color_rgb_u8, "color_rgb_u8", channels=3, dtype=np.uint8, size=size)
        depth = check_image(depth_m, "depth_m", size=size)
        if not np.issubdtype(depth.dtype, np.floating):
            check_image(depth, "depth_m", dtype=np.float32)  # names the expected dtype
        light = None
        if light_direction_world is not None:
            light = np.asarray(light_direction_world, dtype=np.float64).reshape(-1)
            if light.shape != (3,) or not np.all(np.isfinite(light)) or not np.any(light):
                raise CheckError(
                    "light_direction_world",
                    f"expected a finite non-zero 3-vector, got {light_direction_world!r}",
                )
        return self.process_validated(
            depth, None if pose is None else check_rigid(pose, "pose"), light
        )

    def process_validated(
        self,
        depth_m: np.ndarray,
        pose: np.ndarray | None,
        light_direction_world: np.ndarray | None = None,
    ) -> SurfaceOutput:
        """`process` for input that passed the pipeline's edge (Pipeline.process): depth
        (H, W) float metres of the camera's size, pose rigid or None, light unit or None.

        The first frame gets the identity pose (the world frame is the first camera frame);
        while V is still empty, frames keep the current pose and start the map. A frame that
        cannot be tracked keeps the previous pose, is not fused, and reports tracking_ok
        False with the reason in `tracking`.
        """
        t0 = time.perf_counter()
        if not self.params.use_volume:
            return self._without_volume(pose)
        c = self.params
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth_m) & (depth_m >= c.depth_min_m) & (depth_m <= c.depth_max_m)
        n_valid = int(np.count_nonzero(valid))
        depth_clean = np.where(valid, depth_m, 0.0).astype(np.float32)
        tracking = TrackingResult(True)
        if pose is not None:
            self.pose = pose
        elif self.frame_index > 0 and self.num_blocks > 0:
            depth_image = o3d.t.geometry.Image(o3c.Tensor(depth_clean, device=self.device))
            tracking = self._tracker.track(depth_image, n_valid, self._model_depth)
            if tracking.ok and tracking.prev_from_cur is not None:  # (ok: it is set)
                self.pose = self.pose @ tracking.prev_from_cur
        # (pose None and V still empty: this frame starts the map at the current pose)
        if tracking.ok and self._last is not None and self._still.may_reuse(self.pose):
            return self._reused(self._last, tracking, (time.perf_counter() - t0) * 1e3)
        if tracking.ok and n_valid > 0:
            self._volume.integrate(depth_clean, self.pose)
        self._volume.sync()
        t1 = time.perf_counter()

        depth_v, normals_v = self._volume.ray_cast(self.pose, surface_subsample(c, self.camera))
        self._model_depth = (
            None if self.num_blocks == 0 else o3c.Tensor(depth_v, device=self.device)
        )
        aux = self._aux.update(self._volume, self.pose, depth_v, light_direction_world)
        self._volume.sync()
        t2 = time.perf_counter()

        self.frame_index += 1
        out = SurfaceOutput(
            pose=self.pose.copy(),
            depth_volume_m=depth_v,
            normals_volume=normals_v,
            aux_buffers=aux,
            tracking_ok=tracking.ok,
            timings_ms={"Reconstruct": (t1 - t0) * 1e3, "Surface": (t2 - t1) * 1e3},
            tracking=tracking,
        )
        if tracking.ok and self.num_blocks > 0:
            self._last = out
            self._still.did_work(self.pose)
        return out

    def _reused(
        self, last: SurfaceOutput, tracking: TrackingResult, elapsed_ms: float
    ) -> SurfaceOutput:
        """A still camera's frame: tracked, not fused; `last` cast's D_v, N_v and aux."""
        self.frame_index += 1
        return SurfaceOutput(
            self.pose.copy(),
            last.depth_volume_m,
            last.normals_volume,
            list(last.aux_buffers),
            True,
            {"Reconstruct": elapsed_ms, "Surface": 0.0},
            tracking,
            reused=True,
        )

    def _without_volume(self, pose: np.ndarray | None) -> SurfaceOutput:
        """use_volume False: no V, no tracking; the given pose (or the last one) is kept."""
        if pose is not None:
            self.pose = pose
        ok = pose is not None or self.frame_index == 0
        tracking = TrackingResult(
            ok, reason="" if ok else "no volume to track against (use_volume false) and no pose"
        )
        self.frame_index += 1
        h, w = self.camera.height, self.camera.width
        return SurfaceOutput(
            self.pose.copy(),
            np.zeros((h, w), np.float32),
            np.zeros((h, w, 3), np.float32),
            [],
            ok,
            {"Reconstruct": 0.0, "Surface": 0.0},
            tracking,
        )
