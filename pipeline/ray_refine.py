"""Ray-cast refinement: D_v and N_v on the trilinear TSDF from Open3D's ray cast hits.

Open3D 0.20's ray caster finds the zero crossing of the TSDF sampled at the voxel corner
below each ray step (nearest neighbour), off by up to a voxel; frame-to-model tracking
turns that bias into a pose offset. A Numba kernel (written once, `register_jitable`, CPU
driver here; a numba.cuda driver can reuse it) corrects each hit with one Newton step.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange
from numba.extending import register_jitable

from arlight.core.camera import PinholeCamera

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
def _refine_cpu(
    raw, source, index, mask, ratio, rot, fx, fy, cx, cy, voxel, max_step, depth, normals
):
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
            t, gx, gy, gz = _refine_pixel(
                t, source, index, mask, ratio, y, x, d0, d1, d2, voxel, max_step
            )
            depth[y, x] = t
            norm = math.sqrt(gx * gx + gy * gy + gz * gz)
            if norm > 0.0:
                for i in range(3):  # camera frame: rot^T g
                    normals[y, x, i] = (rot[0, i] * gx + rot[1, i] * gy + rot[2, i] * gz) / norm


def refine_ray_cast(
    raw_depth_m: np.ndarray,
    source: np.ndarray,
    index: np.ndarray,
    mask: np.ndarray,
    ratio: np.ndarray,
    world_from_cam: np.ndarray,
    camera: PinholeCamera,
    voxel_size_m: float,
) -> tuple[np.ndarray, np.ndarray]:
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
    _refine_cpu(
        np.ascontiguousarray(raw_depth_m, np.float32),
        np.ascontiguousarray(source, np.float32),
        np.ascontiguousarray(index, np.int64),
        np.ascontiguousarray(mask, np.bool_),
        np.ascontiguousarray(ratio, np.float32),
        np.ascontiguousarray(world_from_cam[:3, :3], np.float64),
        float(camera.fx),
        float(camera.fy),
        float(camera.cx),
        float(camera.cy),
        float(voxel_size_m),
        REFINE_MAX_STEP_VOXELS * voxel_size_m,
        depth,
        normals,
    )
    return depth, normals
