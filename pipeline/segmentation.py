"""Material segments: regions likely to share one albedo, for the light estimate.

Light scales a Lambertian pixel's RGB by its shading, so regions of one chromaticity that
do not cross depth edges are taken as one material. Uses OpenCV's graph-based segmentation
(Felzenszwalb-Huttenlocher, opencv-contrib `ximgproc`) on two colour features and scaled
log-depth. Colour features: "invariant" (default), log chromaticity across the Planckian
(daylight) direction with a small weight along it, so a sky-lit (bluish) shadow stays with
the sun-lit floor around it; or "chroma", plain rg chromaticity, which white light leaves
unchanged but which splits such shadows off as materials of their own."""

from __future__ import annotations

import cv2
import numpy as np

# chromaticity channels are scaled to 0..255; log-depth so that a 10 % depth jump is a
# step as large as a clear colour change
_CHROMA_SCALE = 3.0 * 255.0
_LOG_DEPTH_SCALE = 300.0
# "invariant" features: daylight of different colour temperature (warm sun, blue sky) moves
# (log R/G, log B/G) of linear sRGB along the Planckian direction, about (-1, 1.5) (from
# blackbody white points: 5000 K ~ (1.0, 0.86, 0.67), 10000 K ~ (0.73, 0.83, 1.0)); the
# component across it barely moves, so a sky-lit shadow keeps the value of the sun-lit
# ground around it, while the component along it is kept with a small weight
_PLANCKIAN = np.array([-1.0, 1.5]) / np.hypot(1.0, 1.5)
_INVARIANT_SCALE = 80.0
ILLUMINANT_WEIGHT = 4.0  # feature levels per unit of log chromaticity along it


# the graph threshold (given for scale 2) and the smallest segment, in pixels of the image given
SEGMENT_K = 300.0
SEGMENT_MIN_SIZE_PX = 200


def material_segments(
    color_linear: np.ndarray,
    depth_m: np.ndarray,
    *,
    scale: int = 2,
    k: float = SEGMENT_K,
    min_size_px: int = SEGMENT_MIN_SIZE_PX,
    features: str = "invariant",
    illuminant_weight: float = ILLUMINANT_WEIGHT,
) -> np.ndarray:
    """(H, W) int32 labels >= 0 of likely-uniform-albedo regions.

    color_linear: (H, W, 3) linear RGB; depth_m: (H, W) metres (0 = missing);
    features: "invariant" or "chroma" (module docstring); illuminant_weight: "invariant"
    only, feature levels per unit of log chromaticity along the daylight direction.
    Runs at 1/`scale` resolution for speed and upsamples the labels (nearest); k (the
    Felzenszwalb-Huttenlocher threshold, per pixel of a segment) is given for scale 2 and
    min_size_px in full-resolution pixels, both converted so that segments keep their size
    at any scale.
    """
    h, w = depth_m.shape
    small_c = color_linear[::scale, ::scale].astype(np.float32)
    small_d = depth_m[::scale, ::scale].astype(np.float32)
    log_d = np.where(small_d > 0, np.log(np.maximum(small_d, 1e-3)), 0.0)
    depth_feat = np.clip((log_d + 3.0) * _LOG_DEPTH_SCALE / 10.0, 0, 255)
    if features == "chroma":
        chroma = small_c / (small_c.sum(axis=-1, keepdims=True) + 1e-3)
        feat = np.stack(
            [chroma[..., 0] * _CHROMA_SCALE, chroma[..., 1] * _CHROMA_SCALE, depth_feat], axis=-1
        )
    elif features == "invariant":
        c = small_c + 1e-3
        log_rg, log_bg = np.log(c[..., 0] / c[..., 1]), np.log(c[..., 2] / c[..., 1])
        across = _PLANCKIAN[1] * log_rg - _PLANCKIAN[0] * log_bg  # barely moved by daylight
        along = _PLANCKIAN[0] * log_rg + _PLANCKIAN[1] * log_bg
        feat = np.stack(
            [128.0 + _INVARIANT_SCALE * across, 128.0 + illuminant_weight * along, depth_feat],
            axis=-1,
        )
    else:
        raise ValueError(f"features must be 'chroma' or 'invariant', got {features!r}")
    feat = np.ascontiguousarray(np.clip(feat, 0, 255).astype(np.uint8))
    # the smallest segment in full-resolution pixels, whatever the scale
    min_size = max(1, round(min_size_px / (scale * scale)))
    k_scaled = k * 4.0 / (scale * scale)
    seg = cv2.ximgproc.segmentation.createGraphSegmentation(
        sigma=0.8, k=k_scaled, min_size=min_size
    )
    labels = seg.processImage(feat).astype(np.int32)
    full = np.repeat(np.repeat(labels, scale, axis=0), scale, axis=1)
    return np.ascontiguousarray(full[:h, :w])
