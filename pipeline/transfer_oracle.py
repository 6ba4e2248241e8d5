"""The plain NumPy/Python oracle of the radiance transfer (`transfer_reference`), the
definition the Numba kernels of `radiance_transfer.py` are tested against."""

from __future__ import annotations

import math

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.pipeline import sh
from arlight.pipeline.config import TransferParams
from arlight.pipeline.horizon import SupportPlane
from arlight.pipeline.transfer_sampling import SamplingPattern, visibility_ramp
from arlight.pipeline.transfer_types import (
    BIAS_ABS_M,
    BIAS_REL,
    HORIZON_BELOW_M,
    AuxBufferArrays,
    TransferResult,
)


def _occlusion_reference(x: np.ndarray, s: np.ndarray, w: np.ndarray, chi: float) -> float:
    """K of eq. 7-8 (NumPy): occluding surface point s (3,) seen from x (3,) towards w (3,)."""
    t = s - x
    norm = float(np.linalg.norm(t))
    if norm < 1e-9:
        return 1.0
    return min(chi, 1.0 - float(t @ w) / norm) / chi


def _visibility_reference(
    x: np.ndarray,
    w: np.ndarray,
    radius: float,
    depth: np.ndarray,
    camera: PinholeCamera,
    aux: AuxBufferArrays,
    chi: float,
    thickness: float,
) -> float:
    """K in [0, 1] of one sample y = x + radius * w against the main and auxiliary buffers."""
    y = x + radius * w
    k = 1.0
    h, width = depth.shape
    if y[2] > 1e-6:
        u = int(round(camera.fx * y[0] / y[2] + camera.cx))
        v = int(round(camera.fy * y[1] / y[2] + camera.cy))
        if 0 <= u < width and 0 <= v < h:
            sz = float(depth[v, u])
            if 0.0 < sz < y[2] - (BIAS_ABS_M + BIAS_REL * y[2]) and sz > y[2] - thickness:
                s = np.array(
                    [(u - camera.cx) / camera.fx * sz, (v - camera.cy) / camera.fy * sz, sz]
                )
                k = min(k, _occlusion_reference(x, s, w, chi))
    for b in range(aux.depth.shape[0]):
        rot, trans = aux.buffer_from_cam[b, :, :3], aux.buffer_from_cam[b, :, 3]
        q = rot @ y + trans  # sample in the buffer frame
        r = aux.depth.shape[1]
        half = 0.5 * (r - 1)
        pix = float(aux.pixel_size[b])
        ub, vb = int(round(q[0] / pix + half)), int(round(q[1] / pix + half))
        if 0 <= ub < r and 0 <= vb < r:
            sd = float(aux.depth[b, vb, ub])
            if 0.0 < sd < q[2] - (BIAS_ABS_M + BIAS_REL * 0.5 * sd) and sd > q[2] - thickness:
                s_buffer = np.array([(ub - half) * pix, (vb - half) * pix, sd])
                s = rot.T @ (s_buffer - trans)  # back into the camera frame
                k = min(k, _occlusion_reference(x, s, w, chi))
    return k


def transfer_reference(
    points_cam: np.ndarray,
    normals_cam: np.ndarray,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    pattern: SamplingPattern,
    aux: AuxBufferArrays | None,
    params: TransferParams,
    plane: SupportPlane | None = None,
) -> TransferResult:
    """Plain NumPy/Python oracle of :func:`compute_transfer`: same inputs, same definition
    (the transfer only, not the bounce).

    A straightforward loop over grid pixels, directions and steps; very slow, for tests on
    tiny images only.
    """
    points = np.asarray(points_cam, dtype=np.float32).astype(np.float64)
    normals = np.asarray(normals_cam, dtype=np.float32).astype(np.float64)
    depth = points[..., 2]
    h, w = depth.shape
    step = params.rt_subsample
    hs, ws = (h + step - 1) // step, (w + step - 1) // step
    u_grid = np.array([min(j * step + step // 2, w - 1) for j in range(ws)])
    v_grid = np.array([min(i * step + step // 2, h - 1) for i in range(hs)])
    dirs = np.asarray(pattern.directions, dtype=np.float64)
    rot_world_cam = np.asarray(world_from_cam, dtype=np.float64)[:3, :3]
    ysh = sh.sh_basis(dirs @ rot_world_cam.T, params.sh_bands)  # basis in the WORLD frame
    aux = aux if aux is not None else AuxBufferArrays.empty()
    weight = 4.0 * math.pi / len(dirs)
    transfer = np.zeros((hs, ws, ysh.shape[1]))
    valid = np.zeros((hs, ws), dtype=bool)
    for i, vi in enumerate(v_grid):
        for jj, ui in enumerate(u_grid):
            x, n = points[vi, ui], normals[vi, ui]
            if not x[2] > 0.0 or not np.any(n != 0.0):
                continue
            valid[i, jj] = True
            up = plane.up if plane is not None and plane.height(x) > -HORIZON_BELOW_M else None
            for j, wdir in enumerate(dirs):
                cos_n = float(wdir @ n)
                if not cos_n > 0.0 or (up is not None and float(wdir @ up) < 0.0):
                    continue
                k = 1.0
                if params.visibility:
                    for s in range(pattern.radii.shape[3]):
                        radius = float(pattern.radii[vi % 2, ui % 2, j, s])
                        k = min(
                            k,
                            _visibility_reference(
                                x,
                                wdir,
                                radius,
                                depth,
                                camera,
                                aux,
                                visibility_ramp(pattern, params),
                                params.rt_thickness_m,
                            ),
                        )
                transfer[i, jj] += k * cos_n * weight * ysh[j]
    return TransferResult(transfer.astype(np.float32), valid, u_grid, v_grid)
