"""Equirectangular HDR environment maps and the lighting truth they give.

Conventions (those of ``../shared/data/synthetic`` and of Mitsuba's ``envmap`` emitter): a
direction d in the map's own frame shows column u = (atan2(d.x, -d.z) / 2 pi) mod 1 and row
v = acos(d.y) / pi (row 0 at the top); a map rotated by phi about world +Y lights the world
direction R_y(phi) d. Radiance is linear RGB in the file's own units. The truth is computed
over every texel with its exact solid angle, in arlight's SH basis (no Condon-Shortley
phase) by the pipeline's own SH code; :func:`to_file_convention` converts it for
``lighting_gt.json``, which, as the shared set, stores Sloan's basis WITH the phase.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from arlight.pipeline import sh
from arlight.pipeline.color import LUMA

SH_BANDS = 4
MAP_SUFFIXES = (".hdr", ".exr")


class MapError(ValueError):
    """An environment map that cannot be used (missing, unreadable, not 2:1)."""


def load_map(path: str | Path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an equirectangular .hdr or .exr map; W == 2 H."""
    path = Path(path)
    if not path.is_file():
        raise MapError(f"--map {path}: no such file (give an equirectangular .hdr or .exr)")
    if path.suffix.lower() not in MAP_SUFFIXES:
        raise MapError(f"--map {path}: must be a Radiance .hdr or OpenEXR .exr file")
    if path.suffix.lower() == ".exr":
        from arlight.sources.exr import read_exr

        rgb = np.asarray(read_exr(path), np.float32)
    else:
        bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if bgr is None or bgr.ndim != 3:
            raise MapError(f"--map {path}: not a readable RGB HDR image")
        rgb = np.ascontiguousarray(bgr[..., ::-1], np.float32)
    h, w = rgb.shape[:2]
    if w != 2 * h:
        raise MapError(
            f"--map {path}: {w}x{h} pixels is not an equirectangular map (width "
            "must be twice the height)"
        )
    if not np.all(np.isfinite(rgb)) or rgb.min() < 0:
        raise MapError(f"--map {path}: holds negative or non-finite radiance")
    return rgb


def rotation_y(phi_deg: float) -> np.ndarray:
    """R_y(phi) (3, 3): right-handed rotation about +Y (world_from_map)."""
    c, s = math.cos(math.radians(phi_deg)), math.sin(math.radians(phi_deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@functools.lru_cache(maxsize=8)
def texel_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (H, W, 3) of the texel centres in the map's frame, and each row's
    texel solid angle (H,) in steradians (exact: the texels tile the sphere)."""
    theta = (np.arange(height) + 0.5) / height * math.pi
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], -1)
    edges = np.arange(height + 1) / height * math.pi
    solid = (2 * math.pi / width) * (np.cos(edges[:-1]) - np.cos(edges[1:]))
    return dirs, solid


def map_direction_to_pixel(
    direction_map: np.ndarray, height: int, width: int
) -> tuple[float, float]:
    """(column, row) in pixels (continuous, texel centres at +0.5) of a map-frame direction."""
    d = np.asarray(direction_map, float) / np.linalg.norm(direction_map)
    u = (math.atan2(d[0], -d[2]) / (2 * math.pi)) % 1.0
    v = math.acos(float(np.clip(d[1], -1, 1))) / math.pi
    return u * width, v * height


@dataclass(frozen=True)
class EnvironmentTruth:
    """SH of one rotated map in the world frame, arlight's basis (no phase), bands 0..3.

    sh_rgb_world (3, 16) per linear channel; sh_lum_world (16,) luminance; sh_lum_upper_world
    (16,) of the radiance over world y > 0 only (zero below): the light that can reach a
    scene on the ground plane.
    """

    sh_rgb_world: np.ndarray
    sh_lum_world: np.ndarray
    sh_lum_upper_world: np.ndarray


def world_texels(shape: tuple[int, ...], rotation_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit world directions (H*W, 3) of a map's texels rotated by `rotation_deg` about +Y,
    and each texel's solid angle (H*W,) in steradians."""
    h, w = shape[:2]
    dirs, solid = texel_directions(h, w)
    return dirs.reshape(-1, 3) @ rotation_y(rotation_deg).T, np.repeat(solid, w)


def environment_truth(radiance: np.ndarray, rotation_deg: float) -> EnvironmentTruth:
    """The truth of an (H, W, 3) map rotated by `rotation_deg` about world +Y."""
    world, weights = world_texels(radiance.shape, rotation_deg)
    basis = sh.sh_basis(world, SH_BANDS) * weights[:, None]  # (N, 16)
    rgb = radiance.reshape(-1, 3).astype(np.float64)
    sh_rgb = rgb.T @ basis
    lum = rgb @ np.asarray(LUMA, float)
    upper = world[:, 1] > 0
    return EnvironmentTruth(sh_rgb, lum @ basis, lum[upper] @ basis[upper])


def rotate_to_camera(coeffs_world: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """SH of the same distant light in the camera frame (w_cam = R_wc^T w_world)."""
    return sh.rotate(np.asarray(coeffs_world, float), np.asarray(world_from_cam, float)[:3, :3].T)


def dominant(coeffs: np.ndarray) -> np.ndarray:
    """Unit direction towards the light: the normalised first moment (band 1)."""
    return sh.dominant_direction(np.asarray(coeffs, float))


def to_file_convention(coeffs: np.ndarray) -> list:
    """arlight's basis -> Sloan's with the Condon-Shortley phase (lighting_gt.json), rounded."""
    return np.round(sh.toggle_condon_shortley(np.asarray(coeffs, float)), 7).tolist()


@dataclass(frozen=True)
class CompactRegion:
    """The brightest compact region of a map (world frame): direction (3,) unit, the
    luminance-weighted mean of its texels; solid_angle_sr; share: its part of the irradiance
    on a surface facing it from the upper hemisphere (world y > 0); power: its luminance
    integrated over its solid angle (the map's units; the irradiance it brings to a surface
    facing it); rgb: (3,) the same per linear channel (its colour: rgb / power)."""

    direction: np.ndarray
    solid_angle_sr: float
    share: float
    power: float = 0.0
    rgb: np.ndarray = field(default_factory=lambda: np.zeros(3))


# a compact source: texels within this angle of the brightest one, at least this fraction of
# its luminance (the sun's disc and glare, a lamp; docs/synth.md)
REGION_RADIUS_DEG = 8.0
REGION_LEVEL = 0.1


def brightest_compact_region(radiance: np.ndarray, rotation_deg: float) -> CompactRegion:
    """The compact region around the brightest texel above the horizon of an (H, W, 3) map
    rotated by `rotation_deg` about world +Y (the truth a compact light source is judged by)."""
    return compact_regions(radiance, rotation_deg, 1)[0]


def compact_regions(
    radiance: np.ndarray, rotation_deg: float, max_regions: int, min_share: float = 0.0
) -> list[CompactRegion]:
    """Up to `max_regions` compact regions of an (H, W, 3) map rotated by `rotation_deg`
    about world +Y, brightest peak first: each is the first's rule (REGION_RADIUS_DEG,
    REGION_LEVEL) around the brightest texel above the horizon not within REGION_RADIUS_DEG
    of an earlier peak; the list stops at the first whose share is below `min_share` (the
    lamps of a night square, the panels of a studio's softbox)."""
    world, weights = world_texels(radiance.shape, rotation_deg)
    rgb = radiance.reshape(-1, 3).astype(np.float64)
    lum = rgb @ np.asarray(LUMA, float)
    upper = world[:, 1] > 0
    lum_upper = np.where(upper, lum, 0.0)
    free = upper.copy()
    regions: list[CompactRegion] = []
    while len(regions) < max_regions and np.any(free):
        peak = int(np.argmax(np.where(free, lum_upper, -1.0)))
        near = world @ world[peak] > math.cos(math.radians(REGION_RADIUS_DEG))
        region = near & free & (lum >= REGION_LEVEL * lum[peak])
        free &= ~near
        power = lum[region] * weights[region]
        direction = (world[region] * power[:, None]).sum(axis=0)
        direction /= max(float(np.linalg.norm(direction)), 1e-30)
        cos = np.maximum(world @ direction, 0.0)
        total = float(np.sum(lum_upper * weights * cos))
        share = float(np.sum(power * cos[region])) / max(total, 1e-30)
        if regions and share < min_share:
            break
        colour = (rgb[region] * weights[region, None]).sum(axis=0)
        regions.append(
            CompactRegion(
                direction, float(weights[region].sum()), share, float(power.sum()), colour
            )
        )
    return regions
