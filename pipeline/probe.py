"""The Probe stage: a radiance cube map per frame at a point of the room (issue 33).

At `point_world` (by default the centre of the virtual objects' bounding spheres), every
texel direction of a `probe_size`-texel cube (OpenGL faces along the world axes,
`probe_cube`) is followed through the room grid (`probe_grid.RoomGrid`, fused from the
frames' filtered depth and linear colour): a direction that meets a surface takes that
surface's colour, the camera's linear image units, which are the units the light estimate is
in (the renderer shades a Lambertian albedo rho with rho / pi times the estimate's
irradiance, and the estimate is fitted so that this reproduces the real pixels): no further
scale is needed for the two to agree. A direction that leaves the grid sees the distant
light: the estimate's SH (clamped at 0) times its colour, or the streamed panorama's HDR map
when there is one. The mips are GGX-prefiltered (`probe_cube.prefilter`).

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
    memory: fuse every frame (False: the current frame only)."""

    size: int = 64
    room: bool = True
    cells: int = 120
    cell_m: float = 0.04
    memory: bool = True

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

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(K, 3) float32 radiance along world directions (K, 3)."""
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        if self.environment is not None:
            from arlight.pipeline.glossy import mirror

            local = d @ np.asarray(self.environment.map_from_world, np.float64).T
            return np.asarray(mirror(self.environment.pyramid, local), np.float32)
        lum = np.maximum(sh.evaluate(np.asarray(self.sh, np.float64), d), 0.0)
        return (lum[:, None] * np.asarray(self.rgb, np.float64)[None, :]).astype(np.float32)


@dataclass
class ProbeResult:
    """One frame's probe. point_world: (3,) metres; mips: the prefiltered cube (linear image
    units, world axes); grid: the room it was made from (for parallax-corrected lookups);
    distant: the light of the misses; hit_fraction: share of level-0 texels that met the room;
    diagnostics: JSON-ready notes (see the module text)."""

    point_world: np.ndarray
    mips: CubeMips
    grid: RoomGrid | None
    distant: DistantLight
    hit_fraction: float
    diagnostics: dict[str, Any]


class ProbeStage:
    """The probe of one session: its grid, fused every frame (not thread-safe)."""

    def __init__(self, settings: ProbeSettings, camera: PinholeCamera):
        self.settings = settings
        self.camera = camera
        self.grid: RoomGrid | None = None
        self._dirs = probe_cube.texel_directions(settings.size).reshape(-1, 3)

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
        radiance = distant.radiance(self._dirs)
        hit_fraction = 0.0
        if grid is not None:
            t, rgb = grid.march(point, self._dirs)
            hit = np.isfinite(t)
            radiance[hit] = rgb[hit]
            hit_fraction = float(hit.mean())
        diagnostics["hit_fraction"] = round(hit_fraction, 4)
        mips = probe_cube.prefilter(radiance.reshape(6, s.size, s.size, 3))
        return ProbeResult(point, mips, grid, distant, hit_fraction, diagnostics)


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
