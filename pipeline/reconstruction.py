"""Reconstruct and Surface stages: the volume V, G_v = (D_v, N_v) and the auxiliary buffers.

Section 4 of the image-space illumination paper (seeds/000): the static scene is fused into a
TSDF volume V (sparse Open3D ``VoxelBlockGrid``, tensor API, on ``Config.device``), the camera
is tracked frame-to-model against V (projective point-to-plane ICP, Open3D's multi-scale RGB-D
odometry), and V is ray-cast into the current view to give the geometry buffer
``G_v = (D_v, N_v)``. Section 5.1 adds orthographic geometry buffers extracted from V: left,
right and top of the camera frustum, and one seen from the dominant light.

Frames and units: metres; camera axes are OpenCV (x right, y down, z forward); poses are
``world_from_cam`` (camera-to-world) 4x4 float64. The world frame is the first frame's camera
frame unless poses are supplied.

Orthographic buffers are rendered by z-buffer splatting of the TSDF's zero crossings, sampled
every `aux_stride()` voxels (about half a buffer pixel apart), keeping only surfaces seen from
their front (free) side, so a wall seen from behind is transparent. (Ray casting V with a
distant telephoto pinhole was tried and rejected: Open3D's ray caster skips empty blocks in
whole-block steps and so jumps over thin TSDF bands seen at other angles than the fusing
camera's, leaving striped holes.)

Open3D 0.20 behaviours this module corrects or avoids, each measured on exact synthetic
depth (tests/test_reconstruction.py):
- integration reads the depth pixel by truncating the projected coordinates (a half-pixel
  shift of the fused surface, hence of every tracked pose): integrate with cx, cy + 0.5;
- the ray caster samples the TSDF at the voxel corner below each step (surface off by up to a
  voxel): one Newton step on the trilinear TSDF (`refine_ray_cast`, a Numba kernel);
- block allocation looks at every 4th pixel only (last rows/columns lose their blocks): a
  second, shifted pass;
- the ray caster's range map overruns for image sizes that are not multiples of 8 (holes or
  a hang): cast a padded image;
- its fragment buffer drops a fragment whenever it grows (holes that vary from run to run):
  reserve it once per session;
- odometry sums with a TBB reduction (poses vary by ~1e-5 m run to run): entry points run
  Open3D on one thread (`arlight.pipeline.runtime.configure_open3d_threads`); this module
  never changes that process-wide setting.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba
import numpy as np
import open3d as o3d
import open3d.core as o3c
from numba import prange
from numba.extending import register_jitable

from arlight.pipeline.camera import PinholeCamera
from arlight.pipeline.config import Config
from arlight.pipeline.splat import splat_nearest

# The Open3D releases whose behaviours (listed above) this module was measured against and
# corrects; another release may have fixed one (the correction would then shift the surface)
OPEN3D_SUPPORTED = ((0, 20), (0, 21))  # [from, to)


def _check_open3d_version(version: str = o3d.__version__) -> None:
    major_minor = tuple(int(x) for x in version.split(".")[:2])
    low, high = OPEN3D_SUPPORTED
    if not low <= major_minor < high:
        raise ImportError(
            f"arlight.pipeline.reconstruction supports open3d >={low[0]}.{low[1]},"
            f"<{high[0]}.{high[1]} (it corrects that release's ray casting and integration), "
            f"found {version}; install it with: pip install 'open3d>={low[0]}.{low[1]},"
            f"<{high[0]}.{high[1]}'")


_check_open3d_version()

# Frame-to-model tracking (projective point-to-plane ICP, coarse to fine: 3 pyramid levels).
TRACKING_ITERATIONS = (6, 3, 1)  # Open3D's t.pipelines.slam defaults
# fewer ICP inliers than this fraction of the valid input depth pixels: failure (a good
# frame has 0.8-1; a 30 cm / 6 degree jump of 7-Scenes frames that ICP cannot bridge, 0.2)
TRACKING_MIN_INLIER_FRACTION = 0.3
TRACKING_MAX_STEP_M = 0.3  # a larger jump between consecutive frames is a failure
TRACKING_MAX_STEP_RAD = np.deg2rad(30.0)
TRACKING_MIN_VALID_PIXELS = 100  # fewer valid depth pixels (input or model): not tracked

# Ray casting: voxels seen fewer times than this are not surface (ramped up over the first
# frames, as Open3D's slam.Model does, so the first frame already gives D_v).
WEIGHT_THRESHOLD = 3.0

# Open3D's ray-casting range map: one entry per 8 x 8 pixels (its default)
RANGE_MAP_DOWN_FACTOR = 8
# Open3D's VoxelBlockGrid.compute_unique_block_coordinates(depth) looks at every 4th pixel
BLOCK_TOUCH_STRIDE = 4

# Auxiliary buffers: centre at the median of D_v along the optical axis (this when D_v is empty)
AUX_FALLBACK_CENTRE_DEPTH_M = 1.5
AUX_NAMES = ("left", "right", "top", "light")


@dataclass
class OrthoBuffer:
    """An orthographic depth image of the volume V (section 5.1's auxiliary geometry buffers).

    world_from_buffer: (4, 4) float64. Buffer frame: x right, y down, z = viewing direction;
        origin at the centre of the image plane.
    depth_m: (R, R) float32, distance along +z from the image plane to the first surface seen
        from its front side; 0 = no surface.
    pixel_size_m: metres per pixel; the centre of pixel (u, v) (column, row) is at
        x = (u - (R - 1) / 2) * pixel_size_m, y = (v - (R - 1) / 2) * pixel_size_m.
    name: "left", "right", "top" or "light".
    """

    world_from_buffer: np.ndarray
    depth_m: np.ndarray
    pixel_size_m: float
    name: str

    @property
    def resolution(self) -> int:
        return int(self.depth_m.shape[0])

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) as (u, v), float, and depth (...,) along +z of points.

        Round (u, v) to the nearest integer to index ``depth_m[v, u]``; a point is hidden from
        this buffer's direction where its depth exceeds the stored depth.
        """
        p = np.asarray(points_world, dtype=np.float64)
        buffer_from_world = np.linalg.inv(self.world_from_buffer)
        q = p @ buffer_from_world[:3, :3].T + buffer_from_world[:3, 3]
        half = (self.resolution - 1) / 2.0
        uv = q[..., :2] / self.pixel_size_m + half
        return uv, q[..., 2]


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
        frame was not fused into V).
    timings_ms: {"Reconstruct": track + integrate, "Surface": ray cast + aux buffers}.
    """

    pose: np.ndarray
    depth_volume_m: np.ndarray
    normals_volume: np.ndarray
    aux_buffers: list[OrthoBuffer]
    tracking_ok: bool
    timings_ms: dict[str, float] = field(default_factory=dict)


def render_orthographic(points_world: np.ndarray, world_from_buffer: np.ndarray,
                        resolution: int, pixel_size_m: float,
                        max_depth_m: float = np.inf) -> np.ndarray:
    """Z-buffer splatting of a point set into an orthographic depth image (NumPy).

    points_world: (N, 3) metres. world_from_buffer: (4, 4), buffer frame as in OrthoBuffer.
    Each point lands in its nearest pixel; the smallest depth in (0, max_depth_m] wins.
    Returns (resolution, resolution) float32 depth along the buffer's +z, 0 = empty.
    """
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    buffer_from_world = np.linalg.inv(np.asarray(world_from_buffer, dtype=np.float64))
    q = p @ buffer_from_world[:3, :3].T + buffer_from_world[:3, 3]
    half = (resolution - 1) / 2.0
    return splat_nearest(q[:, 0] / pixel_size_m + half, q[:, 1] / pixel_size_m + half, q[:, 2],
                         resolution, resolution, max_depth_m)


def aux_buffer_poses(world_from_cam: np.ndarray, centre_depth_m: float, extent_m: float,
                     light_direction_world: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """world_from_buffer of each auxiliary buffer, centred on a point in front of the camera.

    The covered region is a cube of side extent_m centred at the camera position plus
    centre_depth_m along the optical axis; each buffer's image plane is the cube face on the
    side the buffer looks from, so all surface in the cube lies in front of it (depth in
    [0, extent_m]). Relative to the camera:
      left:  looks along camera +x from its left;  x = -z_cam, y = +y_cam
      right: looks along camera -x from its right; x = +z_cam, y = +y_cam
      top:   looks along camera +y (down in the image) from above; x = +x_cam, y = -z_cam
      light: looks along -light_direction_world (from the light towards the scene); y is the
             camera's y made perpendicular (the camera's x if the light is along y).
    """
    pose = np.asarray(world_from_cam, dtype=np.float64)
    rot = pose[:3, :3]
    ex, ey, ez = rot[:, 0], rot[:, 1], rot[:, 2]
    centre = pose[:3, 3] + ez * centre_depth_m
    axes: dict[str, tuple[np.ndarray, np.ndarray]] = {  # name -> (y axis, z axis) in world
        "left": (ey, ex),
        "right": (ey, -ex),
        "top": (-ez, ey),
    }
    if light_direction_world is not None:
        z = -np.asarray(light_direction_world, dtype=np.float64).reshape(3)
        z = z / np.linalg.norm(z)
        helper = ey if abs(float(ey @ z)) < 0.9 else ex
        y = helper - (helper @ z) * z
        axes["light"] = (y / np.linalg.norm(y), z)
    poses = {}
    for name, (y, z) in axes.items():
        t = np.eye(4)
        t[:3, 0] = np.cross(y, z)
        t[:3, 1] = y
        t[:3, 2] = z
        t[:3, 3] = centre - z * (extent_m / 2.0)
        poses[name] = t
    return poses


def _check_pose(pose: np.ndarray | None, name: str) -> np.ndarray | None:
    if pose is None:
        return None
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite")
    return p


def _padded(size: int) -> int:
    """`size` rounded up to a multiple of RANGE_MAP_DOWN_FACTOR.

    Open3D's ray caster reads its range map (one entry per RANGE_MAP_DOWN_FACTOR^2 pixels)
    at pixel // factor but sizes it size // factor: the last rows or columns of an image
    whose size is not a multiple read past its end, and the cast then returns holes or never
    finishes (seen with 80x60 and 112x84 images). Casting a padded image and cropping it
    avoids that; the principal point stays where it is.
    """
    f = RANGE_MAP_DOWN_FACTOR
    return -(-size // f) * f


def _rotation_angle(rot: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))


# ------------------------------------------------------------------ ray-cast refinement
# Open3D's ray caster finds the zero crossing of the TSDF sampled at the voxel corner below
# each ray step (nearest neighbour), which is off by up to a voxel depending on how the
# surface lies in the grid; frame-to-model tracking turns that bias into a pose offset. One
# Newton step on the trilinearly interpolated TSDF of the hit's cell, along the ray, puts the
# hit on the interpolated surface (exact for planar patches). Per-pixel logic written once
# (register_jitable) for the CPU driver below; a numba.cuda driver can reuse it.

REFINE_MAX_STEP_VOXELS = 2.0  # a larger Newton step is not trusted: the raw hit is kept


@register_jitable
def _refine_pixel(t, source, index, mask, ratio, y, x, d0, d1, d2, voxel, max_step):
    """Refined depth and unnormalised TSDF gradient (world, per voxel) at pixel (y, x).

    Corner k = dx + 2 dy + 4 dz of the hit's cell has the value source[index[y, x, k]] and
    the trilinear weight ratio[y, x, k]; (d0, d1, d2) is the world ray per metre of depth.
    Unobserved corners (mask False) are left out of the gradient, as Open3D's normals do,
    and disable the depth step."""
    fx = ratio[y, x, 1] + ratio[y, x, 3] + ratio[y, x, 5] + ratio[y, x, 7]
    fy = ratio[y, x, 2] + ratio[y, x, 3] + ratio[y, x, 6] + ratio[y, x, 7]
    fz = ratio[y, x, 4] + ratio[y, x, 5] + ratio[y, x, 6] + ratio[y, x, 7]
    phi = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    complete = True
    for k in range(8):
        if not mask[y, x, k]:
            complete = False
            continue
        value = source[index[y, x, k]]
        bx = k & 1
        by = (k >> 1) & 1
        bz = (k >> 2) & 1
        wx = fx if bx == 1 else 1.0 - fx
        wy = fy if by == 1 else 1.0 - fy
        wz = fz if bz == 1 else 1.0 - fz
        phi += ratio[y, x, k] * value
        gx += (2 * bx - 1) * wy * wz * value
        gy += (2 * by - 1) * wx * wz * value
        gz += (2 * bz - 1) * wx * wy * value
    if complete:
        slope = (gx * d0 + gy * d1 + gz * d2) / voxel  # d(tsdf) / d(depth)
        if slope < 0.0:
            step = -phi / slope
            if abs(step) <= max_step:
                t = t + step
    return t, gx, gy, gz


@numba.njit(parallel=True, cache=True)
def _refine_cpu(raw, source, index, mask, ratio, rot, fx, fy, cx, cy, voxel, max_step,
                depth, normals):
    h, w = raw.shape
    for row in prange(h):
        y = np.int64(row)
        for x in range(w):
            t = raw[y, x]
            if not t > 0.0:  # no hit (0) or NaN
                continue
            rx = (x - cx) / fx
            ry = (y - cy) / fy
            d0 = rot[0, 0] * rx + rot[0, 1] * ry + rot[0, 2]
            d1 = rot[1, 0] * rx + rot[1, 1] * ry + rot[1, 2]
            d2 = rot[2, 0] * rx + rot[2, 1] * ry + rot[2, 2]
            t, gx, gy, gz = _refine_pixel(t, source, index, mask, ratio, y, x, d0, d1, d2,
                                          voxel, max_step)
            depth[y, x] = t
            norm = math.sqrt(gx * gx + gy * gy + gz * gz)
            if norm > 0.0:
                for i in range(3):  # camera frame: rot^T g
                    normals[y, x, i] = (rot[0, i] * gx + rot[1, i] * gy + rot[2, i] * gz) / norm


def refine_ray_cast(raw_depth_m: np.ndarray, source: np.ndarray, index: np.ndarray,
                    mask: np.ndarray, ratio: np.ndarray, world_from_cam: np.ndarray,
                    camera: PinholeCamera, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """D_v and N_v from Open3D's ray cast ("depth", "index", "mask", "interp_ratio").

    raw_depth_m: (H, W) depth of the ray caster, 0 = no hit. source: the TSDF values indexed
    by index (H, W, 8) int64 (corner k = dx + 2 dy + 4 dz of the hit's cell); mask (H, W, 8)
    bool: the corner is observed; ratio (H, W, 8): trilinear weights of the hit.
    Returns depth (H, W) float32 metres (0 = none) and unit outward normals (H, W, 3)
    float32 in the camera frame (zeros where none).
    """
    h, w = raw_depth_m.shape
    depth = np.zeros((h, w), np.float32)
    normals = np.zeros((h, w, 3), np.float32)
    _refine_cpu(np.ascontiguousarray(raw_depth_m, np.float32),
                np.ascontiguousarray(source, np.float32), np.ascontiguousarray(index, np.int64),
                np.ascontiguousarray(mask, np.bool_), np.ascontiguousarray(ratio, np.float32),
                np.ascontiguousarray(world_from_cam[:3, :3], np.float64), float(camera.fx),
                float(camera.fy), float(camera.cx), float(camera.cy), float(voxel_size_m),
                REFINE_MAX_STEP_VOXELS * voxel_size_m, depth, normals)
    return depth, normals


class VolumeReconstruction:
    """One session's volume V: tracking, TSDF fusion, ray casting and auxiliary buffers.

    config: volume parameters (voxel size config.voxel_size_m, sparse blocks of
        config.block_resolution^3 voxels with an initial hash-map capacity of
        config.block_count blocks, which grows when exceeded; TSDF truncation
        config.sdf_trunc_voxels voxels; depth range config.depth_min_m..depth_max_m).
        V is not clipped to a volume_size_m cube: that size only sets the voxel size, and
        V extends wherever depth within depth_max_m is seen (see num_blocks).
    camera: intrinsics of the depth images (registered to colour).

    One instance per session; not safe to call from several threads at once.
    """

    def __init__(self, config: Config, camera: PinholeCamera):
        self.config = config
        self.camera = camera
        self.device = o3c.Device(config.device)
        if self.device.get_type() == o3c.Device.DeviceType.CUDA and not o3c.cuda.is_available():
            raise RuntimeError(
                f"config.device is {config.device!r} but this Open3D build has no CUDA device; "
                "use device='CPU:0'")
        self._intrinsic = o3c.Tensor(camera.matrix, o3c.float64)  # stays on the host
        # Open3D's integration reads the depth pixel a voxel projects into by truncating its
        # projected coordinates, i.e. half a pixel to the upper left of the nearest one;
        # integrating with the principal point moved by +0.5 px makes that the nearest pixel
        # (without it the fused surface, and every tracked pose, is offset by ~z / (2 f)).
        k_integrate = camera.matrix.copy()
        k_integrate[:2, 2] += 0.5
        self._intrinsic_integrate = o3c.Tensor(k_integrate, o3c.float64)
        self._no_color = o3d.t.geometry.Image(
            o3c.Tensor.zeros((camera.height, camera.width, 1), o3c.uint8, self.device))
        self._criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n)
                          for n in TRACKING_ITERATIONS]
        self._loss = o3d.t.pipelines.odometry.OdometryLossParams(  # Open3D's 7 cm : 5 cm
            depth_outlier_trunc=config.tracking_depth_diff_m,
            depth_huber_delta=config.tracking_depth_diff_m * 5.0 / 7.0)
        self.reset()

    def reset(self) -> None:
        """Forget the volume, the pose and the cached buffers (a new session)."""
        c = self.config
        self._grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=["tsdf", "weight"], attr_dtypes=[o3c.float32, o3c.float32],
            attr_channels=[[1], [1]], voxel_size=c.voxel_size_m,
            block_resolution=c.block_resolution, block_count=c.block_count,
            device=self.device)
        self._reserve_range_map()
        self.pose = np.eye(4)  # world_from_cam of the latest frame
        self.frame_index = 0  # frames processed
        self.frames_integrated = 0
        self._model_depth: o3c.Tensor | None = None  # D_v of the previous frame, on device
        self._aux_cache: list[OrthoBuffer] = []
        self._aux_age = 0  # frames since the aux buffers were rendered

    def _reserve_range_map(self) -> None:
        """Grow Open3D's ray-casting fragment buffer once, up front, to config.block_count.

        VoxelBlockGrid.ray_cast keeps a buffer of range-map fragments (about one per block in
        view) and, when a cast needs more than it holds, drops one fragment of that cast (which
        one depends on thread timing: holes in D_v that differ from run to run) and enlarges
        the buffer for the next call. Casting once against block_count placeholder blocks in
        front of the camera (not inserted into V) sizes it so that this does not happen while
        fewer blocks are in view.
        """
        cam, c = self.camera, self.config
        block_m = c.voxel_size_m * c.block_resolution
        # one layer of blocks filling the view, far enough to hold block_count of them (one
        # thin layer keeps the cast itself short: every ray stops after a block or two)
        view = (cam.width / cam.fx) * (cam.height / cam.fy)
        z = int(np.ceil(np.sqrt(c.block_count / view))) + 2
        zc = (z + 0.5) * block_m
        xs = np.arange(np.floor(-cam.cx / cam.fx * zc / block_m),
                       np.ceil((cam.width - 1 - cam.cx) / cam.fx * zc / block_m))
        ys = np.arange(np.floor(-cam.cy / cam.fy * zc / block_m),
                       np.ceil((cam.height - 1 - cam.cy) / cam.fy * zc / block_m))
        gx, gy = np.meshgrid(xs, ys)
        keys = o3c.Tensor(np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
                          .astype(np.int32), o3c.int32, self.device)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            self._grid.ray_cast(keys, self._intrinsic, o3c.Tensor(np.eye(4)),
                                _padded(cam.width), _padded(cam.height), ["depth"], 1.0,
                                c.depth_min_m, 2.0 * zc + 1.0, 1.0, c.sdf_trunc_voxels,
                                RANGE_MAP_DOWN_FACTOR)

    @property
    def voxel_grid(self) -> o3d.t.geometry.VoxelBlockGrid:
        """The TSDF volume V ("tsdf" and "weight" per voxel), e.g. to export a mesh."""
        return self._grid

    @property
    def num_blocks(self) -> int:
        """Voxel blocks allocated in V so far (memory: block_resolution^3 * 8 bytes each)."""
        return int(self._grid.hashmap().size())

    # ---------------------------------------------------------------- per frame
    def process(self, color_rgb_u8: np.ndarray, depth_m: np.ndarray, pose: np.ndarray | None,
                light_direction_world: np.ndarray | None = None) -> SurfaceOutput:
        """Track (unless pose is given), fuse the frame into V, ray-cast G_v and aux buffers.

        color_rgb_u8: (H, W, 3) uint8 RGB (validated; only depth is fused into V).
        depth_m: (H, W) float32 metres along the optical axis, 0 or NaN = missing.
        pose: (4, 4) world_from_cam, or None to track frame-to-model against the previous
            frame's D_v (the first frame gets the identity: the world frame is the first
            camera frame; while V is still empty, frames keep the current pose and start the
            map). A frame that cannot be tracked (too little depth, ICP failure, implausible
            jump) keeps the previous pose, is not fused, and reports tracking_ok False.
        light_direction_world: unit vector towards the dominant light, or None (no "light"
            buffer).
        """
        cam = self.camera
        depth = np.asarray(depth_m)
        if depth.shape != (cam.height, cam.width):
            raise ValueError(f"depth_m must have shape ({cam.height}, {cam.width}), "
                             f"got {depth.shape}")
        if not np.issubdtype(depth.dtype, np.floating):
            raise ValueError(f"depth_m must be floating-point metres, got dtype {depth.dtype} "
                             "(convert uint16 depth with its depth_scale first)")
        color = np.asarray(color_rgb_u8)
        if color.shape != (cam.height, cam.width, 3) or color.dtype != np.uint8:
            raise ValueError(f"color_rgb_u8 must be uint8 of shape ({cam.height}, {cam.width}, "
                             f"3), got {color.dtype} {color.shape}")
        pose = _check_pose(pose, "pose")
        light = None
        if light_direction_world is not None:
            light = np.asarray(light_direction_world, dtype=np.float64).reshape(-1)
            if light.shape != (3,) or not np.all(np.isfinite(light)) or not np.any(light):
                raise ValueError("light_direction_world must be a finite non-zero 3-vector, "
                                 f"got {light_direction_world!r}")

        c = self.config
        t0 = time.perf_counter()
        tracking_ok = True
        if not c.use_volume:
            if pose is not None:
                self.pose = pose
            tracking_ok = pose is not None or self.frame_index == 0
            self.frame_index += 1
            h, w = cam.height, cam.width
            return SurfaceOutput(self.pose.copy(), np.zeros((h, w), np.float32),
                                 np.zeros((h, w, 3), np.float32), [], tracking_ok,
                                 {"Reconstruct": 0.0, "Surface": 0.0})

        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth) & (depth >= c.depth_min_m) & (depth <= c.depth_max_m)
        n_valid = int(np.count_nonzero(valid))
        depth_clean = np.where(valid, depth, 0.0).astype(np.float32)
        depth_image = o3d.t.geometry.Image(o3c.Tensor(depth_clean, device=self.device))
        if pose is not None:
            self.pose = pose
        elif self.frame_index > 0 and self.num_blocks > 0:
            tracking_ok = self._track(depth_image, n_valid)
        # (pose None and V still empty: this frame starts the map at the current pose)
        if tracking_ok and n_valid > 0:
            self._integrate(depth_clean)
        self._sync()
        t1 = time.perf_counter()

        depth_v, normals_v = self._ray_cast_view()
        aux = self._aux_buffers(depth_v, light)
        self._sync()
        t2 = time.perf_counter()

        self.frame_index += 1
        return SurfaceOutput(
            pose=self.pose.copy(), depth_volume_m=depth_v, normals_volume=normals_v,
            aux_buffers=aux, tracking_ok=tracking_ok,
            timings_ms={"Reconstruct": (t1 - t0) * 1e3, "Surface": (t2 - t1) * 1e3})

    # ---------------------------------------------------------------- stages
    def _sync(self) -> None:
        if self.device.get_type() == o3c.Device.DeviceType.CUDA:
            o3c.cuda.synchronize(self.device)

    def _track(self, depth_image: o3d.t.geometry.Image, n_valid: int) -> bool:
        """Frame-to-model ICP against the previous frame's D_v; updates self.pose on success."""
        model = self._model_depth
        if model is None or n_valid < TRACKING_MIN_VALID_PIXELS:
            return False
        if int((model > 0).to(o3c.int64).sum().item()) < TRACKING_MIN_VALID_PIXELS:
            return False
        odometry = o3d.t.pipelines.odometry
        try:
            # point-to-plane odometry reads depth only; the colour slot holds a placeholder
            result = odometry.rgbd_odometry_multi_scale(
                o3d.t.geometry.RGBDImage(self._no_color, depth_image),
                o3d.t.geometry.RGBDImage(self._no_color, o3d.t.geometry.Image(model)),
                self._intrinsic, o3c.Tensor(np.eye(4)), 1.0, self.config.depth_max_m,
                self._criteria, odometry.Method.PointToPlane, self._loss)
        except RuntimeError:
            return False
        prev_from_cur = result.transformation.numpy()
        # Open3D's fitness is inliers per image pixel; relate it to the pixels with depth
        inlier_fraction = result.fitness * self.camera.width * self.camera.height / n_valid
        if (not np.all(np.isfinite(prev_from_cur))
                or inlier_fraction < TRACKING_MIN_INLIER_FRACTION
                or np.linalg.norm(prev_from_cur[:3, 3]) > TRACKING_MAX_STEP_M
                or _rotation_angle(prev_from_cur[:3, :3]) > TRACKING_MAX_STEP_RAD):
            return False
        self.pose = self.pose @ prev_from_cur
        return True

    def _integrate(self, depth_m: np.ndarray) -> bool:
        """Fuse depth (H, W) float32 metres (0 = missing) into V at self.pose."""
        c, cam = self.config, self.camera
        extrinsic = o3c.Tensor(np.linalg.inv(self.pose))
        depth_image = o3d.t.geometry.Image(o3c.Tensor(depth_m, device=self.device))
        # Open3D allocates blocks around pixels (s i, s j), i < H // s, j < W // s (stride
        # s = BLOCK_TOUCH_STRIDE), so the last rows and columns can be left without blocks;
        # a second pass over the image cropped and zero-padded to put them on that grid
        # covers them.
        s = BLOCK_TOUCH_STRIDE
        sy, sx = (cam.height - 1) % s, (cam.width - 1) % s
        k_shifted = cam.matrix.copy()
        k_shifted[0, 2] -= sx
        k_shifted[1, 2] -= sy
        shifted = np.pad(depth_m[sy:, sx:], ((0, s), (0, s)))
        passes = [(depth_image, self._intrinsic),
                  (o3d.t.geometry.Image(o3c.Tensor(shifted, device=self.device)),
                   o3c.Tensor(k_shifted))]
        found = []
        for image, intrinsic in passes:
            try:
                found.append(self._grid.compute_unique_block_coordinates(
                    image, intrinsic, extrinsic, 1.0, c.depth_max_m, c.sdf_trunc_voxels))
            except RuntimeError:  # Open3D aborts when no block is touched (nothing in range)
                pass
        if not found:
            return False
        blocks = found[0]
        if len(found) > 1:
            keys = np.unique(np.concatenate([b.cpu().numpy() for b in found]), axis=0)
            blocks = o3c.Tensor(keys.astype(np.int32), o3c.int32, self.device)
        self._grid.integrate(blocks, depth_image, self._intrinsic_integrate, extrinsic, 1.0,
                             c.depth_max_m, c.sdf_trunc_voxels)
        self.frames_integrated += 1
        return True

    def _weight_threshold(self) -> float:
        return max(1.0, min(float(self.frames_integrated), WEIGHT_THRESHOLD))

    def _active_blocks(self) -> o3c.Tensor:
        hashmap = self._grid.hashmap()
        return hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)]

    def _ray_cast_view(self) -> tuple[np.ndarray, np.ndarray]:
        """D_v (H, W) and N_v (H, W, 3) of V at self.pose; D_v also stays on the device as the
        model frame the next frame is tracked against (see :func:`refine_ray_cast`)."""
        cam, c = self.camera, self.config
        h, w = cam.height, cam.width
        self._model_depth = None
        if self.num_blocks == 0:
            return np.zeros((h, w), np.float32), np.zeros((h, w, 3), np.float32)
        hp, wp = _padded(h), _padded(w)
        # Open3D warns while it grows its range-map buffer; that is expected, not a problem
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            result = self._grid.ray_cast(
                self._active_blocks(), self._intrinsic, o3c.Tensor(np.linalg.inv(self.pose)),
                wp, hp, ["depth", "index", "mask", "interp_ratio"], 1.0, c.depth_min_m,
                c.depth_max_m, self._weight_threshold(), c.sdf_trunc_voxels,
                RANGE_MAP_DOWN_FACTOR)
        tsdf = self._grid.attribute("tsdf")
        if self.device.get_type() == o3c.Device.DeviceType.CPU:
            source, index = tsdf.numpy().reshape(-1), result["index"].numpy()[:h, :w]
        else:  # gather the 8 corner values on the device; only they travel to the host
            source = tsdf.reshape((-1,))[result["index"].reshape((-1,))].cpu().numpy()
            index = np.arange(hp * wp * 8, dtype=np.int64).reshape(hp, wp, 8)[:h, :w]
        depth, normals = refine_ray_cast(
            result["depth"].cpu().numpy()[:h, :w, 0], source, index,
            result["mask"].cpu().numpy()[:h, :w], result["interp_ratio"].cpu().numpy()[:h, :w],
            self.pose, cam, c.voxel_size_m)
        self._model_depth = o3c.Tensor(depth, device=self.device)
        return depth, normals

    def _aux_buffers(self, depth_v: np.ndarray, light: np.ndarray | None) -> list[OrthoBuffer]:
        c = self.config
        if not c.aux_buffers:
            return []
        names = [b.name for b in self._aux_cache]
        stale = (not self._aux_cache or self._aux_age + 1 >= max(1, c.aux_update_interval)
                 or ("light" in names) != (light is not None))
        if not stale:
            self._aux_age += 1
            return list(self._aux_cache)
        valid = depth_v[depth_v > 0]
        centre = float(np.median(valid)) if valid.size else AUX_FALLBACK_CENTRE_DEPTH_M
        poses = aux_buffer_poses(self.pose, centre, c.aux_extent_m, light)
        pixel = c.aux_extent_m / c.aux_resolution
        points, gradients = self.surface_points(self.aux_stride())
        buffers = []
        for name in AUX_NAMES:
            if name not in poses:
                continue
            world_from_buffer = poses[name]
            # only surfaces seen from their front: the TSDF decreases along the view direction
            front = gradients @ world_from_buffer[:3, 2] < 0
            depth = render_orthographic(points[front], world_from_buffer, c.aux_resolution,
                                        pixel, max_depth_m=c.aux_extent_m)
            buffers.append(OrthoBuffer(world_from_buffer, depth, pixel, name))
        self._aux_cache = buffers
        self._aux_age = 0
        return list(buffers)

    def aux_stride(self) -> int:
        """Voxel step of the surface samples for the auxiliary buffers.

        The largest divisor of block_resolution with samples at most half an aux pixel apart
        and at most the truncation distance apart (so a sign change of the TSDF between two
        samples is always seen with both samples inside the band).
        """
        c = self.config
        pixel = c.aux_extent_m / c.aux_resolution
        limit = min(0.5 * pixel / c.voxel_size_m, c.sdf_trunc_voxels)
        return max([d for d in range(1, c.block_resolution + 1)
                    if c.block_resolution % d == 0 and d <= limit], default=1)

    def surface_points(self, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Zero crossings of the TSDF of V, on the voxel grid sub-sampled every `stride` voxels.

        Returns world points (M, 3) float32, metres, and TSDF gradients (M, 3) float32 at the
        lower sample of each crossing (unnormalised, pointing towards free space; zero
        components where a neighbour sample is unobserved). Crossings are searched along x, y
        and z between consecutive samples of weight >= the ray-casting weight threshold,
        across block borders, and placed by linear interpolation, as Open3D's
        VoxelBlockGrid.extract_point_cloud does at stride 1; a stride > 1 reads stride^3
        fewer voxels.
        """
        c = self.config
        r = c.block_resolution
        if stride < 1 or r % stride:
            raise ValueError(f"stride must divide block_resolution={r}, got {stride}")
        empty = np.zeros((0, 3), np.float32)
        hashmap = self._grid.hashmap()
        buf = hashmap.active_buf_indices().to(o3c.int64)
        if buf.shape[0] == 0:
            return empty, empty
        keys_t = hashmap.key_tensor()[buf]
        keys = keys_t.cpu().numpy().astype(np.int64)  # (N, 3) block coordinates x, y, z
        tsdf_attr = self._grid.attribute("tsdf")  # (capacity, r, r, r, 1): block, z, y, x
        weight_attr = self._grid.attribute("weight")
        threshold = self._weight_threshold()
        sub = slice(None, None, stride)

        on_cpu = self.device.get_type() == o3c.Device.DeviceType.CPU
        if on_cpu:  # zero-copy views; NumPy gathers blocks far faster than Open3D on the CPU
            tsdf_np, weight_np = tsdf_attr.numpy(), weight_attr.numpy()

        def read(index: o3c.Tensor, axis: int | None = None) -> tuple[np.ndarray, np.ndarray]:
            """Sub-sampled tsdf and validity of blocks; only the first layer along `axis`."""
            key: list = [slice(None), sub, sub, sub, 0]
            if axis is not None:
                key[axis] = 0
            if on_cpu:
                rows = index.numpy()
                t, w = tsdf_np[rows][tuple(key)], weight_np[rows][tuple(key)]
            else:
                t = tsdf_attr[index][tuple(key)].cpu().numpy()
                w = weight_attr[index][tuple(key)].cpu().numpy()
            return t, w >= threshold

        tsdf, valid = read(buf)  # (N, m, m, m), array axes: block, z, y, x
        n, m = tsdf.shape[0], r // stride
        # values of the next sample along x, y, z (array axes 3, 2, 1), across block borders
        nxt, nxt_valid = [], []
        for k in range(3):
            axis = 3 - k
            shifted = keys.copy()
            shifted[:, k] += 1
            nb_buf, found = hashmap.find(o3c.Tensor(shifted.astype(np.int32), o3c.int32,
                                                    self.device))
            found_np = found.cpu().numpy()
            layer = np.zeros((n, m, m), np.float32)
            layer_valid = np.zeros((n, m, m), bool)
            if found_np.any():
                t, v = read(nb_buf.to(o3c.int64)[found], axis)
                layer[found_np], layer_valid[found_np] = t, v
            rest = [slice(None)] * 4
            rest[axis] = slice(1, None)
            nxt.append(np.concatenate([tsdf[tuple(rest)], np.expand_dims(layer, axis)], axis))
            nxt_valid.append(np.concatenate([valid[tuple(rest)],
                                             np.expand_dims(layer_valid, axis)], axis))
        # sample index (z, y, x) in a block -> voxel offset (x, y, z) of the sample
        iz, iy, ix = np.meshgrid(*(np.arange(m) * stride,) * 3, indexing="ij")
        points, gradients = [], []
        for k in range(3):
            b, z, y, x = np.nonzero(valid & nxt_valid[k] & (tsdf * nxt[k] < 0))
            a = tsdf[b, z, y, x]
            ratio = a / (a - nxt[k][b, z, y, x])
            voxel = (keys[b] * r + np.stack([ix[z, y, x], iy[z, y, x], iz[z, y, x]], -1)
                     ).astype(np.float64)
            voxel[:, k] += stride * ratio
            points.append(voxel * c.voxel_size_m)
            # forward differences at the lower sample (0 where a neighbour is unobserved)
            gradients.append(np.stack(
                [np.where(nxt_valid[j][b, z, y, x], nxt[j][b, z, y, x] - a, 0.0)
                 for j in range(3)], -1))
        return (np.concatenate(points).astype(np.float32),
                np.concatenate(gradients).astype(np.float32))
