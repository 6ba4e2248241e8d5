"""LDR panoramas made from HDR ones (a camera's exposure and clipping), and a built-in sky.

`ldr_frame(hdr, key)` is what a conventional 360-degree camera records of a linear HDR
environment: an exposure that maps the median luminance (over the sphere, each pixel weighted
by its solid angle) to `key` (0.18 = mid grey), clipping to [0, 1], the sRGB transfer curve
(IEC 61966-2-1) and rounding to 8 bits. `benchmarks/ibl_truth.py` and the tests make their
LDR input this way from the shared HDR maps.

`synthetic_sky` is a procedural HDR sky in the panorama frame (+y up): a sun disc with its
aureole, a sky brighter towards the horizon and a uniform grey ground below it; `arlight
ibl` runs on it when given no panorama, and its HDR map is the truth the command's output
is compared against.
"""

from __future__ import annotations

import math

import numpy as np

from arlight.pipeline import equirect
from arlight.pipeline.color import LUMA

SUN_RADIUS_RAD = math.radians(1.5)  # wider than the real 0.27 deg so that it spans pixels


def keyed_exposure(hdr: np.ndarray, key: float = 0.18) -> float:
    """The factor that maps the solid-angle-weighted median luminance of `hdr` to `key`."""
    image = equirect.check_equirect(hdr, "hdr")
    lum = (np.asarray(image, dtype=np.float64) @ LUMA).reshape(-1)
    weights = equirect.pixel_solid_angles(*image.shape[:2]).reshape(-1)
    order = np.argsort(lum, kind="stable")
    cum = np.cumsum(weights[order])
    median = float(lum[order][np.searchsorted(cum, 0.5 * cum[-1])])
    if not median > 0.0:
        raise ValueError("the map's median luminance is 0: no exposure maps it to a key")
    return key / median


def linear_to_srgb_u8(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] (values outside are clipped) -> 8-bit sRGB, rounded (IEC 61966-2-1)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    encoded = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1.0 / 2.4) - 0.055)
    return np.round(encoded * 255.0).astype(np.uint8)


def ldr_frame(hdr: np.ndarray, key: float = 0.18, exposure: float | None = None) -> np.ndarray:
    """(H, W, 3) uint8 sRGB of a linear HDR map: exposure (`keyed_exposure` unless given),
    clipping, sRGB, 8 bits."""
    scale = keyed_exposure(hdr, key) if exposure is None else exposure
    return linear_to_srgb_u8(np.asarray(hdr, dtype=np.float64) * scale)


def sun_direction(elevation_rad: float, azimuth_rad: float) -> np.ndarray:
    """Unit direction at `elevation_rad` above the horizon, `azimuth_rad` from -z towards +x
    (the map's column u = azimuth / 2 pi)."""
    c = math.cos(elevation_rad)
    return np.array(
        [c * math.sin(azimuth_rad), math.sin(elevation_rad), -c * math.cos(azimuth_rad)]
    )


def synthetic_sky(
    width: int = 512, sun: np.ndarray | None = None, sun_radiance: float = 2000.0
) -> np.ndarray:
    """(width / 2, width, 3) float32 linear HDR sky: sun disc, aureole, sky, ground.

    sun: unit direction towards the sun (default 35 degrees up, azimuth 60 degrees);
    sun_radiance: the disc's radiance relative to the zenith sky (~0.3 blue-white): with
    the defaults the sun disc carries about 80 % of the irradiance of a surface facing it.
    """
    if width < 2 or width % 2:
        raise ValueError(f"width must be even and >= 2, got {width}")
    s = np.asarray(
        sun if sun is not None else sun_direction(math.radians(35), math.radians(60)),
        dtype=np.float64,
    )
    s = s / np.linalg.norm(s)
    d = equirect.pixel_directions(width // 2, width)
    y = d[..., 1]
    cos_sun = np.clip(d @ s, -1.0, 1.0)
    angle = np.arccos(cos_sun)
    horizon = np.exp(-np.maximum(y, 0.0) / 0.25)  # brighter towards the horizon
    sky = np.array([0.18, 0.28, 0.45])[None, None, :] + 0.35 * horizon[..., None] * np.array(
        [1.0, 0.95, 0.85]
    )
    aureole = 4.0 * np.exp(-angle / math.radians(6.0))[..., None] * np.array([1.0, 0.9, 0.7])
    disc = (angle <= SUN_RADIUS_RAD)[..., None] * sun_radiance * np.array([1.0, 0.95, 0.85])
    upper = sky + aureole + disc
    ground = np.broadcast_to(np.array([0.12, 0.10, 0.08]), upper.shape)
    out = np.where((y >= 0.0)[..., None], upper, ground)
    return out.astype(np.float32)
