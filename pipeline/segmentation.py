"""Material segments: regions likely to share one albedo, for the light estimate.

White-ish light scales a Lambertian pixel's RGB by its shading but keeps its
chromaticity, so regions of constant chromaticity that do not cross depth edges are taken
as one material. Uses OpenCV's graph-based segmentation (Felzenszwalb-Huttenlocher,
opencv-contrib `ximgproc`) on (chromaticity r, chromaticity g, scaled log-depth).
"""

from __future__ import annotations

import cv2
import numpy as np

# chromaticity channels are scaled to 0..255; log-depth so that a 10 % depth jump is a
# step as large as a clear colour change
_CHROMA_SCALE = 3.0 * 255.0
_LOG_DEPTH_SCALE = 300.0


def material_segments(color_linear: np.ndarray, depth_m: np.ndarray, *, scale: int = 2,
                      k: float = 300.0, min_size: int = 50) -> np.ndarray:
    """(H, W) int32 labels >= 0 of likely-uniform-albedo regions.

    color_linear: (H, W, 3) linear RGB; depth_m: (H, W) metres (0 = missing).
    Runs at 1/`scale` resolution for speed and upsamples the labels (nearest).
    """
    h, w = depth_m.shape
    small_c = color_linear[::scale, ::scale].astype(np.float32)
    small_d = depth_m[::scale, ::scale].astype(np.float32)
    chroma = small_c / (small_c.sum(axis=-1, keepdims=True) + 1e-3)
    log_d = np.where(small_d > 0, np.log(np.maximum(small_d, 1e-3)), 0.0)
    feat = np.stack([chroma[..., 0] * _CHROMA_SCALE, chroma[..., 1] * _CHROMA_SCALE,
                     np.clip((log_d + 3.0) * _LOG_DEPTH_SCALE / 10.0, 0, 255)], axis=-1)
    feat = np.ascontiguousarray(np.clip(feat, 0, 255).astype(np.uint8))
    seg = cv2.ximgproc.segmentation.createGraphSegmentation(sigma=0.8, k=k, min_size=min_size)
    labels = seg.processImage(feat).astype(np.int32)
    full = np.repeat(np.repeat(labels, scale, axis=0), scale, axis=1)
    return np.ascontiguousarray(full[:h, :w])
