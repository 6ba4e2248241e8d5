"""Auxiliary orthographic geometry buffers of the volume V (section 5.1 of seeds/000).

Left, right and top of the camera frustum, and one seen from the dominant light, rendered
by z-buffer splatting of the TSDF's zero crossings (`TsdfVolume.surface_points`), sampled
every `aux_stride()` voxels (about half a buffer pixel apart), keeping only surfaces seen
from their front (free) side, so a wall seen from behind is transparent. (Ray casting V with
a distant telephoto pinhole was tried and rejected: Open3D's ray caster skips empty blocks in
whole-block steps and so jumps over thin TSDF bands seen at other angles than the fusing
camera's, leaving striped holes.)

Frames and units: metres; poses are world_from_buffer / world_from_cam 4x4 float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arlight.pipeline.config import AuxBufferParams, VolumeParams
from arlight.pipeline.splat import splat_nearest
from arlight.pipeline.volume import TsdfVolume

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


def render_orthographic(
    points_world: np.ndarray,
    world_from_buffer: np.ndarray,
    resolution: int,
    pixel_size_m: float,
    max_depth_m: float = np.inf,
) -> np.ndarray:
    """Z-buffer splatting of a point set into an orthographic depth image (NumPy).

    points_world: (N, 3) metres. world_from_buffer: (4, 4), buffer frame as in OrthoBuffer.
    Each point lands in its nearest pixel; the smallest depth in (0, max_depth_m] wins.
    Returns (resolution, resolution) float32 depth along the buffer's +z, 0 = empty.
    """
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    buffer_from_world = np.linalg.inv(np.asarray(world_from_buffer, dtype=np.float64))
    q = p @ buffer_from_world[:3, :3].T + buffer_from_world[:3, 3]
    half = (resolution - 1) / 2.0
    return splat_nearest(
        q[:, 0] / pixel_size_m + half,
        q[:, 1] / pixel_size_m + half,
        q[:, 2],
        resolution,
        resolution,
        max_depth_m,
    )


def aux_buffer_poses(
    world_from_cam: np.ndarray,
    centre_depth_m: float,
    extent_m: float,
    light_direction_world: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
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


def aux_stride(volume: VolumeParams, aux: AuxBufferParams) -> int:
    """Voxel step of the surface samples for the auxiliary buffers.

    The largest divisor of block_resolution with samples at most half an aux pixel apart
    and at most the truncation distance apart (so a sign change of the TSDF between two
    samples is always seen with both samples inside the band).
    """
    limit = min(0.5 * aux.pixel_size_m / volume.voxel_size_m, volume.sdf_trunc_voxels)
    r = volume.block_resolution
    return max([d for d in range(1, r + 1) if r % d == 0 and d <= limit], default=1)


class AuxBufferRenderer:
    """The auxiliary buffers of one session, re-rendered every `aux_update_interval` frames
    (or when the light buffer appears or goes) and cached in between."""

    def __init__(self, params: AuxBufferParams):
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._cache: list[OrthoBuffer] = []
        self._age = 0  # frames since the buffers were rendered

    def update(
        self,
        volume: TsdfVolume,
        world_from_cam: np.ndarray,
        depth_v: np.ndarray,
        light: np.ndarray | None,
    ) -> list[OrthoBuffer]:
        """The buffers for this frame: centred on the median of D_v (depth_v, (H, W) metres,
        0 = none) in front of the camera; light: unit vector towards the light or None."""
        c = self.params
        if not c.aux_buffers:
            return []
        names = [b.name for b in self._cache]
        stale = (
            not self._cache
            or self._age + 1 >= max(1, c.aux_update_interval)
            or ("light" in names) != (light is not None)
        )
        if not stale:
            self._age += 1
            return list(self._cache)
        valid = depth_v[depth_v > 0]
        centre = float(np.median(valid)) if valid.size else AUX_FALLBACK_CENTRE_DEPTH_M
        poses = aux_buffer_poses(world_from_cam, centre, c.aux_extent_m, light)
        pixel = c.aux_extent_m / c.aux_resolution
        points, gradients = volume.surface_points(aux_stride(volume.params, c))
        buffers = []
        for name in AUX_NAMES:
            if name not in poses:
                continue
            world_from_buffer = poses[name]
            # only surfaces seen from their front: the TSDF decreases along the view direction
            front = gradients @ world_from_buffer[:3, 2] < 0
            depth = render_orthographic(
                points[front],
                world_from_buffer,
                c.aux_resolution,
                pixel,
                max_depth_m=c.aux_extent_m,
            )
            buffers.append(OrthoBuffer(world_from_buffer, depth, pixel, name))
        self._cache = buffers
        self._age = 0
        return list(buffers)
