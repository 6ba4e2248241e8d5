"""From rendered radiance and clean depth to the 8-bit colour and 16-bit depth a sensor gives.

The models of ``../shared/data/synthetic`` (its README, "Image and depth formation"):

* exposure: one per sequence, the geometric-mean luminance of the scene (non-environment)
  pixels over all frames mapped to 0.18, lowered until at most 3 % of them clip;
* colour: sRGB(clip(exposure x radiance, 0, 1)) + N(0, (1.5/255)^2), rounded to 8 bits;
* depth (Kinect v1): z + N(0, sigma(z)^2), sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m; a 3-5 px
  ragged band removed along depth jumps (|dz| > max(3 cm, 3 % z)) and object/environment
  boundaries; ~1.5 % dropouts (single pixels and small blobs); 0 outside 0.4-4.0 m; quantised
  to 1/5000 m.
"""

from __future__ import annotations

import cv2
import numpy as np

from arlight.pipeline.color import LUMA

DEPTH_SCALE = 5000.0  # units per metre (TUM)
DEPTH_RANGE_M = (0.4, 4.0)
MID_GREY = 0.18
MAX_CLIPPED_FRACTION = 0.03
COLOR_NOISE_SIGMA = 1.5 / 255.0
DROPOUT_FRACTION = 0.015


def choose_exposure(radiances: list[np.ndarray], scene_masks: list[np.ndarray]) -> float:
    """The sequence's exposure scale (dimensionless) from its frames' linear radiance
    (H, W, 3) and masks (H, W) bool of pixels that see the scene, not the environment."""
    pixels = np.concatenate([r[m] for r, m in zip(radiances, scene_masks, strict=True)])
    if len(pixels) == 0:
        pixels = np.concatenate([r.reshape(-1, 3) for r in radiances])
    lum = np.maximum(pixels.astype(np.float64) @ LUMA, 1e-8)
    exposure = MID_GREY / float(np.exp(np.mean(np.log(lum))))
    peak = pixels.max(axis=1).astype(np.float64)
    limit = 1.0 / max(float(np.quantile(peak, 1.0 - MAX_CLIPPED_FRACTION)), 1e-8)
    return min(exposure, limit)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_8bit(radiance: np.ndarray, exposure: float, rng: np.random.Generator | None) -> np.ndarray:
    """(H, W, 3) uint8 sRGB; sensor noise added when `rng` is given."""
    s = srgb_encode(radiance.astype(np.float64) * exposure)
    if rng is not None:
        s = s + rng.normal(0.0, COLOR_NOISE_SIGMA, s.shape)
    return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)


def _boundary(depth: np.ndarray) -> np.ndarray:
    """Pixels beside a depth jump or an object/environment boundary."""
    z = depth.astype(np.float64)
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = np.moveaxis(z, axis, 0)
        da, db = a[1:], a[:-1]
        jump = (np.abs(da - db) > np.maximum(0.03, 0.03 * np.minimum(da, db))) | (
            (da > 0) != (db > 0)
        )
        e = np.moveaxis(edge, axis, 0)
        e[1:] |= jump
        e[:-1] |= jump
    return edge


def kinect_depth(depth_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W) uint16 sensor depth at DEPTH_SCALE units per metre from clean depth (metres)."""
    z = depth_m.astype(np.float64)
    sigma = 0.0012 + 0.0019 * (z - DEPTH_RANGE_M[0]) ** 2
    noisy = z + rng.standard_normal(z.shape) * sigma
    # a ragged band 3-5 px wide: the boundary grown by 1 or 2 px, chosen per pixel
    edge = _boundary(depth_m).astype(np.uint8)
    grown1 = cv2.dilate(edge, np.ones((3, 3), np.uint8))
    grown2 = cv2.dilate(edge, np.ones((5, 5), np.uint8))
    band = np.where(rng.random(z.shape) < 0.5, grown1, grown2).astype(bool)
    drops = rng.random(z.shape) < DROPOUT_FRACTION / 3
    blobs = cv2.dilate(
        drops.astype(np.uint8) * (rng.random(z.shape) < 0.3), np.ones((3, 3), np.uint8)
    ).astype(bool)
    valid = (z > 0) & (noisy >= DEPTH_RANGE_M[0]) & (noisy <= DEPTH_RANGE_M[1])
    valid &= ~band & ~drops & ~blobs
    return np.where(valid, np.rint(noisy * DEPTH_SCALE), 0).astype(np.uint16)


def _uint16(values: np.ndarray, scale: float) -> np.ndarray:
    """values times `scale`, rounded and clipped to 16 bits."""
    return np.clip(np.rint(values.astype(np.float64) * scale), 0, 65535).astype(np.uint16)


def clean_depth_16bit(depth_m: np.ndarray) -> np.ndarray:
    return _uint16(depth_m, DEPTH_SCALE)


ALBEDO_SCALE = 65535  # albedo/*.png: linear albedo times this, 16-bit RGB


def albedo_16bit(albedo: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint16: linear albedo (0..1) times ALBEDO_SCALE, no sRGB curve, no noise."""
    return _uint16(albedo, ALBEDO_SCALE)
