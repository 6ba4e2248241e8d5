"""The composite a session returns while the pipeline has no renderer (no virtual objects yet).

It is the input colour frame with a small inset in the top-left corner: a diffuse white sphere
lit by the estimated light (irradiance from the camera-frame SH, Ramamoorthi-Hanrahan), seen
by the camera, with a dot where the dominant light direction points. The shading is
contrast-stretched between the sphere's darkest and brightest points (darkest drawn at
DARKEST_GREY), so it shows the light's direction and shape, not its absolute intensity.
Differential rendering of virtual objects will replace this.
"""

from __future__ import annotations

import cv2
import numpy as np

from arlight.pipeline import sh

INSET_FRACTION = 0.3  # inset diameter as a fraction of the shorter image side
MIN_INSET_PX = 16
DARKEST_GREY = 0.15  # linear grey of the sphere's darkest point after the stretch


def _sphere_normals(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (size, size, 3) of a sphere facing the camera (OpenCV axes), and a mask."""
    c = (size - 1) / 2.0
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = (u - c) / c, (v - c) / c
    r2 = x * x + y * y
    mask = r2 <= 1.0
    z = -np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))  # towards the camera: the visible hemisphere
    return np.stack([x, y, z], axis=-1), mask


def light_sphere(sh_camera: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(size, size, 3) uint8 sRGB image of a white diffuse sphere under `sh_camera`, and mask."""
    normals, mask = _sphere_normals(size)
    irradiance = sh.evaluate(sh.irradiance_from_radiance(sh_camera), normals[mask])
    shade = np.zeros((size, size), np.float64)
    if irradiance.size:
        lo, hi = float(irradiance.min()), float(irradiance.max())
        stretched = (irradiance - lo) / (hi - lo) if hi - lo > 1e-12 * max(abs(hi), 1.0) \
            else np.ones_like(irradiance)
        shade[mask] = DARKEST_GREY + (1.0 - DARKEST_GREY) * stretched
    srgb = np.where(shade <= 0.0031308, 12.92 * shade, 1.055 * shade ** (1 / 2.4) - 0.055)
    grey = (np.clip(srgb, 0, 1) * 255.0 + 0.5).astype(np.uint8)
    image = np.repeat(grey[..., None], 3, axis=-1)
    direction = sh.dominant_direction(sh_camera)
    if np.any(direction) and direction[2] < 0.2:  # the light is on the camera's side
        c = (size - 1) / 2.0
        centre = (int(round(c + direction[0] * c)), int(round(c + direction[1] * c)))
        cv2.circle(image, centre, max(2, size // 16), (255, 200, 0), -1, cv2.LINE_AA)
    return image, mask


def composite_with_light_inset(color: np.ndarray, sh_camera: np.ndarray) -> np.ndarray:
    """The colour frame (H, W, 3) uint8 RGB with the light sphere inset; a new array."""
    out = np.array(color, dtype=np.uint8, copy=True)
    h, w = out.shape[:2]
    size = int(min(h, w) * INSET_FRACTION)
    if size < MIN_INSET_PX:
        return out
    sphere, mask = light_sphere(np.asarray(sh_camera, dtype=np.float64), size)
    margin = max(2, size // 12)
    region = out[margin:margin + size, margin:margin + size]
    region[mask] = sphere[mask]
    cv2.circle(out, (margin + size // 2, margin + size // 2), size // 2, (255, 255, 255), 1,
               cv2.LINE_AA)
    return out
