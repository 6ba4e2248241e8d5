"""The resolution a frame is analysed at (`work_scale`): Reconstruct to LightEst and the
probe run on the frame reduced by an integer factor; the composite is drawn at the input's.

The reduced camera keeps pixel centres consistent (`PinholeCamera.reduced`): work pixel
(i, j) is the mean of input pixels s i .. s i + s - 1 (rows) and s j .. s j + s - 1
(columns). Colour is averaged in linear light (INTER_AREA of the linear image); depth is the
mean of a block's measured samples where they agree, else its nearest (a depth edge keeps the
foreground instead of inventing a depth between the two sides). Why `fast` analyses at half
resolution: docs/decisions/0041-work-resolution.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from arlight.pipeline.volume import upsample_depth, upsample_normals

# a block's measured depths agree when they spread by less than this share of the nearest
DEPTH_AGREEMENT = 0.03


def work_scale(width: int, work_width: int) -> int:
    """The whole factor a `width`-pixel frame is reduced by to stay at least `work_width`
    pixels wide (0: not reduced)."""
    return max(1, width // work_width) if work_width > 0 else 1


def reduce_depth(depth_m: np.ndarray, scale: int) -> np.ndarray:
    """(ceil(H / scale), ceil(W / scale)) float32 metres (0 = none) of depth (H, W)."""
    if scale == 1:
        return depth_m
    h, w = -(-depth_m.shape[0] // scale), -(-depth_m.shape[1] // scale)
    padded = np.zeros((h * scale, w * scale), np.float32)
    padded[: depth_m.shape[0], : depth_m.shape[1]] = depth_m
    total = np.zeros((h, w), np.float32)
    count = np.zeros((h, w), np.float32)
    nearest = np.full((h, w), np.inf, np.float32)
    farthest = np.zeros((h, w), np.float32)
    for dy in range(scale):  # the block's samples as strided views: no copy of the image
        for dx in range(scale):
            sample = padded[dy::scale, dx::scale]
            measured = sample > 0
            total += sample
            count += measured
            np.minimum(nearest, np.where(measured, sample, np.inf), out=nearest)
            np.maximum(farthest, sample, out=farthest)
    agree = farthest - nearest < DEPTH_AGREEMENT * nearest
    out = np.where(agree, total / np.maximum(count, 1.0), nearest)
    return np.where(count > 0, out, 0.0).astype(np.float32)


def reduce_image(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """`image` (H, W, C) area-averaged to shape (h, w); the same array at its own size."""
    if image.shape[:2] == shape:
        return image
    return cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class WorkFrame:
    """A frame at the work resolution: color (h, w, 3) uint8 sRGB (for the depth filter's
    intensity), color_linear (h, w, 3) float32 linear, depth_m (h, w) float32 metres."""

    color: np.ndarray
    color_linear: np.ndarray
    depth_m: np.ndarray


def reduce_frame(
    color: np.ndarray, color_linear: np.ndarray, depth_m: np.ndarray, scale: int
) -> WorkFrame:
    """The input frame (sRGB, its linear colour, metres) at 1/scale of its resolution."""
    if scale == 1:
        return WorkFrame(color, color_linear, depth_m)
    depth = reduce_depth(depth_m, scale)
    shape = (depth.shape[0], depth.shape[1])
    return WorkFrame(reduce_image(color, shape), reduce_image(color_linear, shape), depth)


def enlarge_geometry(
    depth_m: np.ndarray, normals: np.ndarray, scale: int, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Work-resolution depth (h, w) and normals (h, w, 3) at the input's shape (H, W), for
    the renderer: depth bilinear on smooth surfaces and the block's own across depth edges
    (`volume.upsample_depth`), normals the block's."""
    if scale == 1:
        return depth_m, normals
    return upsample_depth(depth_m, scale, shape), upsample_normals(normals, scale, shape)
