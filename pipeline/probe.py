"""The Probe stage: a radiance cube map per frame at a point of the room (issue 33).

At `point_world` (by default the centre of the virtual objects' bounding spheres), every
texel direction of a `probe_size`-texel cube (OpenGL faces along the world axes,
`probe_cube`) is followed through the room grid (`probe_grid.RoomGrid`, fused from the
frames' filtered depth and linear colour): a direction that meets a surface takes that
surface's colour, the camera's linear image units, which are the units the light estimate is
in (the renderer shades a Lambertian albedo rho with rho / pi times the estimate's
irradiance, and the estimate is fitted so that this reproduces the real pixels): no further
scale is needed for the two to agree. A direction that leaves the grid sees the distant
light: the estimate's SH, Hanning-windowed against its ringing (`hanning`, probe_sh_window)
and clamped at 0, times its colour, or the streamed panorama's HDR map when there is one.
The mips are GGX-prefiltered (`probe_cube.prefilter`) when first read.

Bad input and fallbacks (each recorded in `ProbeResult.diagnostics`, which the pipeline puts
under `FrameResult.diagnostics["probe"]`):
- a point inside real geometry (its cell is surface): the probe is the distant light alone
  (`fallback` "inside_geometry");
- a point behind the camera: kept (the grid remembers what earlier frames saw; directions
  never seen fall to the distant light), `behind_camera` true;
- a point off the grid (it moved more than a quarter of the grid from where the grid was
  made): the grid is made anew about it (`regridded` true);
- no volume (`--set use_volume=false`): no tracked poses to fuse frames with, so the grid
  holds the current frame only (`memory` "current_frame");
- a size outside 32..256 or not a power of two: a ValueError from the config naming
  `probe_size`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.pipeline import probe_cube, sh
from arlight.pipeline.probe_cube import CubeMips
from arlight.pipeline.probe_grid import RoomGrid

INSIDE = "inside_geometry"


@dataclass
class ProbeSettings:
    """size: texels a face (32..256, a power of two); room: directions see the room grid
    (False: the distant light alone, the SH-only baseline); cells, cell_m: the grid;
    memory: fuse every frame (False: the current frame only); sun: the SH light's dominant
    part drawn as a small disc (`split_dominant`) instead of smeared over the sky; window:
    the SH of the misses Hanning-windowed (`hanning`) against its ringing."""

    size: int = 64
    room: bool = True
    cells: int = 120
    cell_m: float = 0.04
    memory: bool = True
    sun: bool = False
    window: bool = True

    def __post_init__(self) -> None:
        self.size = probe_cube.check_size(self.size)


@dataclass
class DistantLight:
    """What a direction that leaves the room sees. sh: (C,) world-frame luminance radiance SH
    in linear image units; rgb: (3,) its colour (luminance 1); environment: optional
    `rendering.EnvironmentMap` (a streamed panorama's HDR map), used instead of the SH."""

    sh: np.ndarray
    rgb: np.ndarray = field(default_factory=lambda: np.ones(3))
    environment: Any = None

    def radiance(self, directions: np.ndarray, basis: np.ndarray | None = None) -> np.ndarray:
        """(K, 3) float32 radiance along world directions (K, 3); basis: optionally their SH
        basis (K, C) already evaluated (`sh.sh_basis`)."""
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        if self.environment is not None:
            from arlight.pipeline.glossy import mirror

            local = d @ np.asarray(self.environment.map_from_world, np.float64).T
            return np.asarray(mirror(self.environment.pyramid, local), np.float32)
        coeffs = np.asarray(self.sh, np.float64)
        if basis is None or basis.shape[1] != len(coeffs):
            basis = sh.sh_basis(d, sh.bands_of(len(coeffs)))
        lum = np.maximum(basis @ coeffs, 0.0)
        return (lum[:, None] * np.asarray(self.rgb, np.float64)[None, :]).astype(np.float32)


@dataclass
class ProbeResult:
    """One frame's probe. point_world: (3,) metres; radiance: (6, n, n, 3) float32 level 0
    (linear image units, world axes, `probe_cube` layout); grid: the room it was made from
    (for parallax-corrected lookups); distant: the distant light as given (the misses see it
    windowed, `hanning`, and with probe_sun its dominant part as a disc); hit_fraction:
    share of level-0 texels that met the room; diagnostics: JSON-ready notes (see the
    module text).

    `mirror` is level 0 alone; `mips` every GGX-prefiltered level, made on first use (10 ms
    at 64 texels on 2 cores): a frame whose objects are all mirrors and that nobody asks the
    mips of does not pay for them (docs/results/probe.md, "The mips on demand")."""

    point_world: np.ndarray
    radiance: np.ndarray
    grid: RoomGrid | None
    distant: DistantLight
    hit_fraction: float
    diagnostics: dict[str, Any]

    @functools.cached_property
    def mirror(self) -> CubeMips:
        """Level 0 only (roughness 0): what a mirror reads."""
        return CubeMips([np.ascontiguousarray(self.radiance, np.float32)], np.zeros(1))

    @functools.cached_property
    def mips(self) -> CubeMips:
        """Level 0 and its GGX-prefiltered levels (`probe_cube.prefilter`)."""
        return probe_cube.prefilter(self.radiance)


class ProbeStage:
    """The probe of one session: its grid, fused every frame (not thread-safe)."""

    def __init__(self, settings: ProbeSettings, camera: PinholeCamera):
        self.settings = settings
        self.camera = camera
        self.grid: RoomGrid | None = None
        self._dirs = probe_cube.texel_directions(settings.size).reshape(-1, 3)
        self._basis: np.ndarray | None = None  # the SH basis at the texels, made on first use

    def _grid_for(self, point: np.ndarray) -> tuple[RoomGrid, bool]:
        s = self.settings
        g = self.grid
        if g is not None and np.all(np.abs(point - g.centre) <= 0.25 * g.cells * g.cell_m):
            return g, False
        regridded = g is not None
        self.grid = RoomGrid(point, s.cells, s.cell_m)
        return self.grid, regridded

    def fuse(
        self,
        point_world: np.ndarray,
        depth_m: np.ndarray,
        colour_linear: np.ndarray,
        world_from_cam: np.ndarray,
    ) -> dict[str, Any]:
        """Fuse one frame into the grid about point_world; the notes of what was done."""
        point = np.asarray(point_world, np.float64)
        grid, regridded = self._grid_for(point)
        if not self.settings.memory:
            grid.weight[...] = 0.0
            grid.invalidate()
        fused = grid.update(depth_m, colour_linear, world_from_cam, self.camera)
        return {"regridded": regridded, "points_fused": fused}

    def probe(
        self,
        point_world: np.ndarray,
        world_from_cam: np.ndarray,
        distant: DistantLight,
        notes: dict[str, Any] | None = None,
    ) -> ProbeResult:
        """The cube map at point_world (after `fuse` of this frame)."""
        point = np.asarray(point_world, np.float64)
        s = self.settings
        light = distant  # as given: what the objects' own surfaces are lit by
        cam_from_world = np.linalg.inv(world_from_cam)
        z_cam = float(cam_from_world[2, :3] @ point + cam_from_world[2, 3])
        diagnostics: dict[str, Any] = {
            "size": s.size,
            "levels": probe_cube.num_levels(s.size),
            "point_world": [round(float(x), 4) for x in point],
            "behind_camera": z_cam <= 0.0,
            "memory": "frames" if s.memory else "current_frame",
            "fallback": None,
            **(notes or {}),
        }
        grid = self.grid if s.room else None
        if grid is not None and grid.occupied(point):
            diagnostics["fallback"] = INSIDE
            grid = None
        bands = sh.bands_of(len(distant.sh))
        if self._basis is None or self._basis.shape[1] != bands * bands:
            self._basis = sh.sh_basis(self._dirs, bands)
        sun = None
        if s.sun and s.room and distant.environment is None:
            direction, intensity, residual = split_dominant(distant.sh)
            if intensity > 0.0:
                sun = direction, intensity
                distant = DistantLight(residual, distant.rgb)
        if s.window and distant.environment is None:
            distant = DistantLight(hanning(distant.sh), distant.rgb)
        radiance = distant.radiance(self._dirs, self._basis)
        if sun is not None:
            radiance += sun_disc(self._dirs, s.size, *sun)[:, None] * np.asarray(
                distant.rgb, np.float32
            )
            diagnostics["sun_world"] = [round(float(x), 4) for x in sun[0]]
        hit_fraction = 0.0
        if grid is not None:
            t, rgb = grid.march(point, self._dirs)
            hit = np.isfinite(t)
            radiance[hit] = rgb[hit]
            hit_fraction = float(hit.mean())
        diagnostics["hit_fraction"] = round(hit_fraction, 4)
        cube = radiance.reshape(6, s.size, s.size, 3)
        return ProbeResult(point, cube, grid, light, hit_fraction, diagnostics)


SUN_RADIUS_RAD = math.radians(2.0)  # the disc the dominant light is drawn as
SUN_SHARE_MAX = 0.8  # of the light's band 0 the disc may take (an ambient part is left)


def split_dominant(coeffs: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """A band-limited light as a delta plus the rest (Sloan, "Stupid SH tricks", 2008):
    (unit direction of the delta (`sh.dominant_direction`), its integrated radiance (the
    least-squares fit of the delta's bands >= 1 to the light's, capped so that the rest
    keeps 1 - SUN_SHARE_MAX of band 0), the rest's coefficients). A mirror then shows a
    small bright source and a darker sky, as the path-traced truth does, where the SH
    itself spreads the source's energy over a quarter of the sky; the sum is the same light
    (the diffuse shading does not change)."""
    c = np.asarray(coeffs, np.float64)
    direction = sh.dominant_direction(c)
    if len(c) < 4 or not np.any(direction):
        return np.zeros(3), 0.0, c.copy()
    y = sh.directional_light(direction, 1.0, sh.bands_of(len(c)))
    fit = float(c[1:] @ y[1:]) / float(y[1:] @ y[1:])
    cap = SUN_SHARE_MAX * max(float(c[0]), 0.0) / float(y[0])
    intensity = float(np.clip(fit, 0.0, cap))
    return direction, intensity, c - intensity * y


def hanning(coeffs: np.ndarray) -> np.ndarray:
    """The SH with band l scaled by (1 + cos(pi l / L)) / 2, L the bands (Sloan, "Stupid SH
    tricks"): band 0 kept, the top band nearly gone, so the clamped negative lobes of a
    band-limited light (black holes in a mirror) shrink, at the cost of sharpness."""
    c = np.asarray(coeffs, np.float64)
    bands = sh.bands_of(len(c))
    l_of = np.concatenate([np.full(2 * band + 1, band) for band in range(bands)])
    return c * (1.0 + np.cos(math.pi * l_of / bands)) / 2.0


def sun_disc(
    directions: np.ndarray, size: int, direction: np.ndarray, intensity: float
) -> np.ndarray:
    """(K,) radiance of a disc of SUN_RADIUS_RAD about `direction` over the cube's texel
    directions, of integrated radiance `intensity` over the texels' exact solid angles."""
    cos = directions @ np.asarray(direction, np.float64)
    inside = cos >= math.cos(SUN_RADIUS_RAD)
    omega = probe_cube.texel_solid_angles(size).reshape(-1)
    if not np.any(inside):  # smaller than a texel: the nearest one
        inside = cos >= cos.max()
    out = np.zeros(len(directions), np.float32)
    out[inside] = intensity / float(omega[inside].sum())
    return out


def objects_centre(spheres: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """The default probe point: the mean centre of the objects' bounding spheres (world)."""
    if not spheres:
        raise ValueError("a probe point needs virtual objects or --probe-at X,Y,Z")
    return np.mean([np.asarray(c, np.float64) for c, _ in spheres], axis=0)


def parse_point(text: str, flag: str = "--probe-at") -> np.ndarray:
    """X,Y,Z (metres, world) -> (3,); ValueError naming the flag."""
    parts = text.split(",")
    try:
        point = np.array([float(p) for p in parts], np.float64)
    except ValueError:
        point = np.zeros(0)
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise ValueError(f"{flag} expects X,Y,Z in metres (world frame), got {text!r}")
    return point


__all__ = [
    "INSIDE",
    "DistantLight",
    "ProbeResult",
    "ProbeSettings",
    "ProbeStage",
    "objects_centre",
    "parse_point",
]
