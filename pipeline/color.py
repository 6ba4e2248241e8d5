"""Colour conversions shared by the stages: one definition of the luma weights.

The pipeline's colour images are (H, W, 3) uint8 RGB, sRGB-encoded (`FrameInput.color`).
"""

from __future__ import annotations

import numpy as np

from arlight.core.checks import check_image

# Rec. 709 / sRGB luma weights of R, G, B (the Y row of the sRGB -> XYZ matrix): linear
# luminance from linear RGB, and the paper's grey levels from 8-bit values
LUMA = np.array([0.2126, 0.7152, 0.0722])


def srgb_to_linear(color_u8: np.ndarray) -> np.ndarray:
    """8-bit sRGB -> linear [0, 1] float32 (IEC 61966-2-1), via a 256-entry table."""
    c = np.arange(256, dtype=np.float64) / 255.0
    table = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)
    return table[np.asarray(color_u8, dtype=np.uint8)]


def intensity_from_rgb(color_rgb_u8: np.ndarray) -> np.ndarray:
    """Grey levels (H, W) float32 in 0..255 from an (H, W, 3) uint8 RGB image.

    The luma weights applied to the 8-bit (gamma-encoded) values, as the paper's thresholds
    lambda_I (eq. 1, 4) are in 8-bit grey levels.
    """
    arr = check_image(color_rgb_u8, "color_rgb_u8", channels=3, dtype=np.uint8)
    return np.ascontiguousarray(arr.astype(np.float32) @ LUMA.astype(np.float32))


def luminance(color_linear: np.ndarray) -> np.ndarray:
    """Linear luminance (...,) float32 of linear RGB (..., 3) float32."""
    return color_linear @ LUMA.astype(np.float32)
