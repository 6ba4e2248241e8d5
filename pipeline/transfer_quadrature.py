"""The exact unoccluded transfer as a control variate (TransferParams.rt_exact_unoccluded):
the clamped-cosine transfer minus the sampling pattern's estimate of it, tabulated over
normals in an octahedral map and added to the transfer samples."""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from arlight.pipeline import sh
from arlight.pipeline.channels import vector_length
from arlight.pipeline.transfer_sampling import SamplingPattern
from arlight.pipeline.transfer_upsampling import TransferSamples, _remap_channels


def unoccluded_quadrature_error(
    normals_world: np.ndarray, directions_world: np.ndarray, bands: int
) -> np.ndarray:
    """(K, C): the exact clamped-cosine transfer of unit normals (K, 3), A_l Y_lm(n)
    (Ramamoorthi and Hanrahan 2001), minus the sampling pattern's estimate of it,
    sum_j max(0, n . w_j) Y(w_j) 4 pi / N, both world frame.

    Added to an SSDO transfer it is a control variate: the unoccluded part becomes exact and
    only the blocked directions keep the N-direction sampling error (which, with one
    direction set for every pixel, is a bias shared by a whole surface, not noise)."""
    n = np.asarray(normals_world, np.float64).reshape(-1, 3)
    dirs = np.asarray(directions_world, np.float64)
    # the (K, N) cosines in float32 (half the time; the sum is then good to ~1e-6)
    cos = np.maximum(n.astype(np.float32) @ dirs.T.astype(np.float32), 0.0)
    estimate = cos @ (sh.sh_basis(dirs, bands) * (4.0 * math.pi / len(dirs))).astype(np.float32)
    per_coeff = np.repeat(sh.lambert_band_factors(bands), [2 * l + 1 for l in range(bands)])
    return sh.sh_basis(n, bands) * per_coeff - estimate


QUADRATURE_TABLE_SIZE = 128  # texels per side of the octahedral table of the correction


def _octahedral_uv(n: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel coordinates (float32) of unit vectors (K, 3) in a size x size octahedral map
    of -n (so normals facing a camera, z < 0, fill the map's centre, away from its seams)."""
    m = np.ascontiguousarray(n, np.float64).reshape(-1, 3)
    map_x = np.empty(len(m), np.float32)
    map_y = np.empty(len(m), np.float32)
    _octahedral_uv_kernel(m, float(size), map_x, map_y)
    return map_x, map_y


@numba.njit(parallel=True, cache=True)
def _octahedral_uv_kernel(n, size, map_x, map_y):
    """`_octahedral_uv` one vector at a time (NumPy's whole-array passes took 4 ms a frame
    for 30000 normals); the same float64 operations in the same order."""
    for i in numba.prange(n.shape[0]):
        mx, my, mz = -n[i, 0], -n[i, 1], -n[i, 2]
        norm = abs(mx) + abs(my) + abs(mz)
        norm = norm if norm > 1e-12 else 1e-12
        x, y = mx / norm, my / norm
        if mz / norm < 0.0:
            fx = (1.0 - abs(y)) * (1.0 if x >= 0 else -1.0)
            fy = (1.0 - abs(x)) * (1.0 if y >= 0 else -1.0)
        else:
            fx, fy = x, y
        map_x[i] = np.float32((fx + 1.0) * 0.5 * size - 0.5)
        map_y[i] = np.float32((fy + 1.0) * 0.5 * size - 0.5)


def _octahedral_directions(size: int) -> np.ndarray:
    """(size, size, 3) unit vectors n at the texel centres of `_octahedral_uv`'s map."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    fx, fy = np.meshgrid(c, c)
    fz = 1.0 - np.abs(fx) - np.abs(fy)
    lower = fz < 0.0
    x = np.where(lower, (1.0 - np.abs(fy)) * np.where(fx >= 0, 1.0, -1.0), fx)
    y = np.where(lower, (1.0 - np.abs(fx)) * np.where(fy >= 0, 1.0, -1.0), fy)
    m = np.stack([x, y, fz], axis=-1)
    return -m / np.linalg.norm(m, axis=-1, keepdims=True)


def quadrature_error_table(
    pattern: SamplingPattern, bands: int, size: int = QUADRATURE_TABLE_SIZE
) -> np.ndarray:
    """(size, size, C) float32: `unoccluded_quadrature_error` of the pattern's directions
    (camera frame) at the texel centres of an octahedral map of normals (camera frame).
    Made once per session: the pattern is fixed in the camera frame."""
    normals = _octahedral_directions(size).reshape(-1, 3)
    table = unoccluded_quadrature_error(normals, pattern.directions, bands)
    return table.reshape(size, size, -1).astype(np.float32)


def with_exact_unoccluded(
    samples: TransferSamples,
    normals_cam: np.ndarray,
    world_from_cam: np.ndarray,
    table: np.ndarray,
) -> TransferSamples:
    """The samples' transfer plus `unoccluded_quadrature_error` of their own normals (the
    control variate, TransferParams.rt_exact_unoccluded): the unoccluded part of each
    vector becomes the exact clamped-cosine transfer; blocked directions keep their SSDO
    estimate. normals_cam: (H, W, 3) camera frame (the samples' pixels index it); table:
    `quadrature_error_table` of the session's pattern (`unoccluded_correction`)."""
    if not len(samples.pixel_v):
        return samples
    n = normals_cam[samples.pixel_v, samples.pixel_u]
    transfer = np.array(samples.transfer, copy=True)
    transfer += unoccluded_correction(n, world_from_cam, table)
    return dataclasses.replace(samples, transfer=transfer)


def unoccluded_correction(
    normals_cam: np.ndarray, world_from_cam: np.ndarray, table: np.ndarray
) -> np.ndarray:
    """(K, C) float32: `unoccluded_quadrature_error` of unit normals (K, 3), camera frame,
    looked up bilinearly in `table` (`quadrature_error_table` of the pattern, camera frame)
    and rotated into the world frame of `world_from_cam`; zero rows for zero normals."""
    n = np.asarray(normals_cam, np.float64).reshape(-1, 3)
    ok = vector_length(n) > 1e-6
    out = np.zeros((len(n), table.shape[2]), np.float32)
    if not ok.any():
        return out
    size = table.shape[0]
    map_x, map_y = _octahedral_uv(n[ok], size)
    # edge texels held (not blended with zero), and the lookups laid out as rows of 256
    # (cv2.remap takes maps shorter than 32767 on each side)
    k = len(map_x)
    rows = -(-k // 256)
    maps = [
        np.pad(np.clip(m, 0.0, size - 1.0), (0, rows * 256 - k)).reshape(rows, 256)
        for m in (map_x, map_y)
    ]
    correction_cam = _remap_channels(table, *maps).reshape(rows * 256, -1)[:k]
    rotation = sh.rotation_matrix(
        np.asarray(world_from_cam, np.float64)[:3, :3], sh.bands_of(table.shape[2])
    ).astype(np.float32)
    out[ok] = correction_cam @ rotation.T
    return out
