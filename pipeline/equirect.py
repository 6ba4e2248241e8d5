"""The equirectangular mapping of a 360-degree panorama: directions, solid angles, resampling.

Frame (the panorama's own, as ``../shared/data/synthetic/README.md`` states it): right-handed,
+y up. A unit direction d shows at

    u = (atan2(d.x, -d.z) / 2 pi) mod 1        (column, 0 at the left edge, growing to the right)
    v = acos(d.y) / pi                          (row, 0 at the top = +y, 1 at the bottom = -y)

so the centre column u = 0.5 looks along +z, u = 0 and 1 along -z, u = 0.25 along +x.
Pixel (row i, column j) of an (H, W) map covers u in [j, j + 1) / W and v in [i, i + 1) / H;
its centre is at ((j + 0.5) / W, (i + 0.5) / H). Maps are (H, W) or (H, W, C) arrays with
W = 2 H; sizes are written W x H (width first), as everywhere in arlight.

Solid angles are exact per pixel (the band of polar angles it spans times 2 pi / W), so they
sum to 4 pi; :func:`downsample` averages with them, so a map's integral over the sphere is
kept by resampling.
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numba
import numpy as np

from arlight.core.checks import CheckError


def check_equirect(image: np.ndarray, field: str) -> np.ndarray:
    """`image` as an (H, W) or (H, W, C) equirectangular map with W = 2 H >= 2.

    Raises `CheckError` naming `field` and the size found. Returns the array (not copied).
    """
    a = np.asarray(image)
    if a.ndim not in (2, 3) or a.shape[0] < 1:
        raise CheckError(field, f"expected an (H, W) or (H, W, C) image, got shape {a.shape}")
    h, w = a.shape[:2]
    if w != 2 * h:
        raise CheckError(
            field, f"an equirectangular panorama is twice as wide as high (2:1), got {w}x{h}"
        )
    return a


def uv_of(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) in [0, 1) x [0, 1] of `directions` (..., 3) (normalised here; zero -> (0.5, 0.5))."""
    d = np.asarray(directions, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1)
    y = np.divide(d[..., 1], n, out=np.zeros_like(n), where=n > 0)
    u = np.mod(np.arctan2(d[..., 0], -d[..., 2]) / (2.0 * math.pi), 1.0)
    v = np.arccos(np.clip(y, -1.0, 1.0)) / math.pi
    return u, v


def directions_of(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) at map coordinates (u, v): the inverse of :func:`uv_of`."""
    u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    theta = np.pi * v  # polar angle from +y
    phi = 2.0 * np.pi * u
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], axis=-1)


@lru_cache(maxsize=16)
def _pixel_directions(height: int, width: int) -> np.ndarray:
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    d = directions_of(u[None, :], v[:, None])
    d.setflags(write=False)
    return d


def pixel_directions(height: int, width: int) -> np.ndarray:
    """Unit directions (H, W, 3) float64 of the pixel centres of an (H, W) map (read-only)."""
    return _pixel_directions(int(height), int(width))


@lru_cache(maxsize=16)
def _row_solid_angles(height: int, width: int) -> np.ndarray:
    edges = np.cos(np.pi * np.arange(height + 1) / height)  # cos of the rows' polar edges
    omega = (edges[:-1] - edges[1:]) * (2.0 * math.pi / width)
    omega.setflags(write=False)
    return omega


def row_solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle (H,) float64, steradians, of one pixel of each row (exact; all sum to 4 pi)."""
    return _row_solid_angles(int(height), int(width))


def pixel_solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle (H, W) float64, steradians, of every pixel (rows repeat; sum 4 pi)."""
    return np.broadcast_to(row_solid_angles(height, width)[:, None], (height, width))


def downsample(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-correct resampling of an equirectangular map to `width` x `height` (smaller or equal).

    Every output pixel is the solid-angle-weighted mean of the input it covers (OpenCV's
    INTER_AREA on the map times each row's solid angle, divided by the same resampling of the
    solid angles), so the integral over the sphere is kept: sum(out * omega_out) equals
    sum(in * omega_in) up to rounding. float32 out (float64 in: float64 out).
    """
    a = check_equirect(image, "image")
    h, w = a.shape[:2]
    if width != 2 * height or height < 1:
        raise ValueError(f"the target must be 2:1, got {width}x{height}")
    if height > h:
        raise ValueError(f"downsample goes to a smaller map: {w}x{h} -> {width}x{height}")
    dtype = np.float64 if a.dtype == np.float64 else np.float32
    if (height, width) == (h, w):
        return a.astype(dtype, copy=True)
    if h % height == 0 and a.ndim == 3 and a.shape[2] == 3 and a.dtype in (np.float32, np.float64):
        # whole blocks (INTER_AREA's exact case): one pass, sums in float64
        out = np.empty((height, width, a.shape[2]), dtype)
        _block_mean(a, row_solid_angles(h, w), h // height, out)
        return out
    omega = row_solid_angles(h, w).astype(dtype)
    weights = np.broadcast_to(omega[:, None], (h, w))
    weighted = a.astype(dtype) * (omega[:, None, None] if a.ndim == 3 else omega[:, None])
    num = cv2.resize(weighted, (width, height), interpolation=cv2.INTER_AREA)
    den = cv2.resize(np.ascontiguousarray(weights), (width, height), interpolation=cv2.INTER_AREA)
    if a.ndim == 3 and num.ndim == 2:  # OpenCV drops a single channel
        num = num[..., None]
    return (num / (den[..., None] if a.ndim == 3 else den)).astype(dtype)


# reassociation only (vectorised sums; NaN and inf keep their IEEE meaning)
@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _block_mean(image, omega, k, out):
    """out[i, j] = the solid-angle-weighted mean of image's k x k block (i, j) of an
    (H, W, 3) map (omega: the rows' solid angles; sums in float64, rows read in order)."""
    for i in range(out.shape[0]):
        acc = np.zeros((out.shape[1], 3))
        weight = 0.0
        for r in range(i * k, (i + 1) * k):
            weight += omega[r] * k
            for j in range(out.shape[1]):
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                for q in range(j * k, (j + 1) * k):
                    s0 += image[r, q, 0]
                    s1 += image[r, q, 1]
                    s2 += image[r, q, 2]
                acc[j, 0] += omega[r] * s0
                acc[j, 1] += omega[r] * s1
                acc[j, 2] += omega[r] * s2
        for j in range(out.shape[1]):
            for c in range(3):
                out[i, j, c] = acc[j, c] / weight


def sample_bilinear(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an equirectangular map at `directions` (..., 3) -> (..., C) or (...).

    As a GPU samples a texture with bilinear filtering: wrapped across the u = 0 / 1 seam,
    clamped (edge rows repeated) at the poles. OpenCV's remap on the map padded that way.
    """
    a = check_equirect(image, "image")
    h, w = a.shape[:2]
    u, v = uv_of(directions)
    shape = u.shape
    src = np.ascontiguousarray(a, dtype=np.float32)
    padded = cv2.copyMakeBorder(src, 0, 0, 1, 1, cv2.BORDER_WRAP)
    padded = cv2.copyMakeBorder(padded, 1, 1, 0, 0, cv2.BORDER_REPLICATE)
    x = (u * w - 0.5 + 1.0).astype(np.float32).reshape(-1, 1)  # +1: the padding
    y = (v * h - 0.5 + 1.0).astype(np.float32).reshape(-1, 1)
    out = cv2.remap(padded, x, y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    channels = () if a.ndim == 2 else (a.shape[2],)
    return out.reshape(shape + channels)


def rotate_about_y(image: np.ndarray, angle_rad: float) -> np.ndarray:
    """The map of the environment rotated by `angle_rad` about +y (right-handed), by a column
    shift of round(angle / 2 pi * W) pixels (exact for multiples of 2 pi / W).

    A direction d of the input shows at R_y(angle) d in the output. R_y(a) turns +z towards
    +x, and u = atan2(x, -z) / 2 pi falls by a / 2 pi: the columns shift to the left.
    """
    a = check_equirect(image, "image")
    shift = int(round(angle_rad / (2.0 * math.pi) * a.shape[1]))
    return np.roll(a, -shift, axis=1)
