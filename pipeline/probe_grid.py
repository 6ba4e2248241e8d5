"""The room around a reflection probe: a coloured occupancy grid fused from the frames.

The TSDF volume V (`volume.py`) holds distance and weight only, no colour, and its mesh costs
about 0.3 s a frame: the probe keeps its own dense grid instead, world-aligned and centred
where it was made, `cells` per side of `cell_m` metres (default 120 of 4 cm: 4.8 m across,
28 MB). Each cell holds a running mean of the linear colour of the points that fell in it and
a weight (observations, capped at `WEIGHT_CAP` so that a changed surface takes over within a
few frames); a cell is surface while its weight is > 0.

Per frame (`update`): the frame's filtered depth G_r is unprojected (every `stride`-th pixel)
with its linear colour; first, cells in front of what the frame sees are carved (a cell
whose centre projects onto a pixel whose depth, the minimum over its 3x3 neighbours, lies
more than `carve_margin_m` plus two cells behind it is emptied: something that moved away is
gone in the next frame), then each point adds its colour to its cell. So the grid holds the
current frame's geometry in view at once and what earlier frames saw elsewhere.

`march` follows rays through the grid cell by cell (Amanatides and Woo's traversal: no cell
skipped; blocks of BLOCK^3 cells without surface crossed in one step) and returns the first
surface cell's distance and colour, or a miss when the ray leaves the grid. Frames: world
(the poses'), metres; colours in linear image units.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np
from numba.extending import register_jitable

from arlight.core.camera import PinholeCamera

WEIGHT_CAP = 8.0  # observations a cell's mean colour remembers at most
BLOCK = 8  # cells a side of the blocks that `march` crosses in one step when empty


@numba.njit(cache=True)
def _fuse_points(depth, colour, stride, world_from_cam, fx, fy, cx, cy, origin, cell, grid, weight):
    """Each valid pixel (every stride-th) adds its linear colour to its cell's running mean
    (sequential: pixels share cells). Returns the number of points fused."""
    dims = weight.shape[0]
    h, w = depth.shape
    fused = 0
    for v in range(0, h, stride):
        for u in range(0, w, stride):
            z = depth[v, u]
            if not (z > 0.0) or not math.isfinite(z):
                continue
            xc = (u - cx) / fx * z
            yc = (v - cy) / fy * z
            idx = np.empty(3, np.int64)
            inside = True
            for k in range(3):
                p = world_from_cam[k, 0] * xc + world_from_cam[k, 1] * yc
                p += world_from_cam[k, 2] * z + world_from_cam[k, 3]
                i = int(math.floor((p - origin[k]) / cell))
                if i < 0 or i >= dims:
                    inside = False
                idx[k] = i
            if not inside:
                continue
            old = weight[idx[0], idx[1], idx[2]]
            new = min(old + 1.0, WEIGHT_CAP)
            a = 1.0 / new
            for c in range(3):
                m = grid[idx[0], idx[1], idx[2], c]
                grid[idx[0], idx[1], idx[2], c] = m + a * (colour[v, u, c] - m)
            weight[idx[0], idx[1], idx[2]] = new
            fused += 1
    return fused


@numba.njit(parallel=True, cache=True)
def _carve(weight, origin, cell, cam_from_world, fx, fy, cx, cy, depth_min, margin):
    """Empty the cells whose centre lies in front of what the camera sees (depth_min: the
    minimum of each pixel's 3x3 neighbours, 0 = unknown). Returns nothing; weight in place."""
    dims = weight.shape[0]
    h, w = depth_min.shape
    for ix in numba.prange(dims):
        x = origin[0] + (ix + 0.5) * cell
        for iy in range(dims):
            y = origin[1] + (iy + 0.5) * cell
            for iz in range(dims):
                if weight[ix, iy, iz] <= 0.0:
                    continue
                z = origin[2] + (iz + 0.5) * cell
                pcx = cam_from_world[0, 0] * x + cam_from_world[0, 1] * y
                pcx += cam_from_world[0, 2] * z + cam_from_world[0, 3]
                pcy = cam_from_world[1, 0] * x + cam_from_world[1, 1] * y
                pcy += cam_from_world[1, 2] * z + cam_from_world[1, 3]
                pcz = cam_from_world[2, 0] * x + cam_from_world[2, 1] * y
                pcz += cam_from_world[2, 2] * z + cam_from_world[2, 3]
                if pcz <= 0.05:
                    continue
                u = int(fx * pcx / pcz + cx + 0.5)
                v = int(fy * pcy / pcz + cy + 0.5)
                if u < 0 or v < 0 or u >= w or v >= h:
                    continue
                d = depth_min[v, u]
                if d > 0.0 and pcz < d - margin:
                    weight[ix, iy, iz] = 0.0


@register_jitable
def _fine(px, py, pz, dx, dy, dz, t_start, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z, weight):
    """Cell-by-cell traversal (Amanatides and Woo) from t_start (cell units) along unit d
    inside the cells [lo, hi) of one block: (t of the first surface cell's entry or -1, its
    indices)."""
    qx, qy, qz = px + t_start * dx, py + t_start * dy, pz + t_start * dz
    ix = min(max(int(math.floor(qx)), lo_x), hi_x - 1)
    iy = min(max(int(math.floor(qy)), lo_y), hi_y - 1)
    iz = min(max(int(math.floor(qz)), lo_z), hi_z - 1)
    sx, tx, ex = _axis(ix, qx, dx, t_start)
    sy, ty, ey = _axis(iy, qy, dy, t_start)
    sz, tz, ez = _axis(iz, qz, dz, t_start)
    t = t_start
    while True:
        if weight[ix, iy, iz] > 0.0:
            return t, ix, iy, iz
        if tx <= ty and tx <= tz:
            t = tx
            ix += sx
            tx += ex
            if ix < lo_x or ix >= hi_x:
                break
        elif ty <= tz:
            t = ty
            iy += sy
            ty += ey
            if iy < lo_y or iy >= hi_y:
                break
        else:
            t = tz
            iz += sz
            tz += ez
            if iz < lo_z or iz >= hi_z:
                break
    return -1.0, 0, 0, 0


@register_jitable
def _march_one(px, py, pz, dx, dy, dz, dims, weight, blocks, block):
    """Two-level traversal from p (cell units) along unit d: blocks of block^3 cells that
    hold no surface are crossed in one step, the others cell by cell (`_fine`). Returns (t
    of the first surface cell's entry in cell units or -1, its indices)."""
    t0, t1 = 0.0, np.inf  # the slab interval of the grid
    for p, d in ((px, dx), (py, dy), (pz, dz)):
        if d != 0.0:
            a = -p / d
            b = (dims - p) / d
            t0 = max(t0, min(a, b))
            t1 = min(t1, max(a, b))
        elif p < 0.0 or p >= dims:
            t1 = -1.0
    if t0 >= t1:
        return -1.0, 0, 0, 0
    nb = blocks.shape[0]
    tb = t0 / block  # t in block units
    qx, qy, qz = px / block + tb * dx, py / block + tb * dy, pz / block + tb * dz
    bx = min(max(int(math.floor(qx)), 0), nb - 1)
    by = min(max(int(math.floor(qy)), 0), nb - 1)
    bz = min(max(int(math.floor(qz)), 0), nb - 1)
    sx, tx, ex = _axis(bx, qx, dx, tb)
    sy, ty, ey = _axis(by, qy, dy, tb)
    sz, tz, ez = _axis(bz, qz, dz, tb)
    while True:
        if blocks[bx, by, bz]:
            t, ix, iy, iz = _fine(
                px,
                py,
                pz,
                dx,
                dy,
                dz,
                tb * block,
                bx * block,
                by * block,
                bz * block,
                min((bx + 1) * block, dims),
                min((by + 1) * block, dims),
                min((bz + 1) * block, dims),
                weight,
            )
            if t >= 0.0:
                return t, ix, iy, iz
        if tx <= ty and tx <= tz:
            tb = tx
            bx += sx
            tx += ex
            if bx < 0 or bx >= nb:
                break
        elif ty <= tz:
            tb = ty
            by += sy
            ty += ey
            if by < 0 or by >= nb:
                break
        else:
            tb = tz
            bz += sz
            tz += ez
            if bz < 0 or bz >= nb:
                break
    return -1.0, 0, 0, 0


@numba.njit(parallel=True, cache=True)
def _block_occupancy(weight, block, out):
    """out[b]: whether any cell of block b (block^3 cells) is surface."""
    dims = weight.shape[0]
    nb = out.shape[0]
    for bx in numba.prange(nb):
        for by in range(nb):
            for bz in range(nb):
                found = False
                for ix in range(bx * block, min((bx + 1) * block, dims)):
                    for iy in range(by * block, min((by + 1) * block, dims)):
                        for iz in range(bz * block, min((bz + 1) * block, dims)):
                            if weight[ix, iy, iz] > 0.0:
                                found = True
                                break
                        if found:
                            break
                    if found:
                        break
                out[bx, by, bz] = found


@register_jitable
def _axis(i, q, d, t0):
    """(step, t of the next cell boundary, t between boundaries) along one axis."""
    if d > 0.0:
        return 1, t0 + (i + 1.0 - q) / d, 1.0 / d
    if d < 0.0:
        return -1, t0 + (i - q) / d, -1.0 / d
    return 0, np.inf, np.inf


@numba.njit(parallel=True, cache=True)
def _march_kernel(
    origins, directions, origin, cell, weight, blocks, block, colour_grid, t_out, rgb_out
):
    """First surface cell along each ray (t_out: distance, metres; inf = none)."""
    dims = weight.shape[0]
    for i in numba.prange(origins.shape[0]):
        t_out[i] = np.inf
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm == 0.0:
            continue
        t, ix, iy, iz = _march_one(
            (origins[i, 0] - origin[0]) / cell,
            (origins[i, 1] - origin[1]) / cell,
            (origins[i, 2] - origin[2]) / cell,
            dx / norm,
            dy / norm,
            dz / norm,
            dims,
            weight,
            blocks,
            block,
        )
        if t >= 0.0:
            t_out[i] = t * cell
            for c in range(3):
                rgb_out[i, c] = colour_grid[ix, iy, iz, c]


class RoomGrid:
    """The coloured occupancy grid around a point (see the module text).

    centre_world: (3,) metres; cells: per side; cell_m: metres. Memory: 16 bytes a cell.
    """

    def __init__(self, centre_world: np.ndarray, cells: int = 120, cell_m: float = 0.04):
        self.cell_m = float(cell_m)
        self.cells = int(cells)
        self.centre = np.asarray(centre_world, np.float64).copy()
        self.origin = self.centre - 0.5 * self.cells * self.cell_m
        self.colour = np.zeros((self.cells,) * 3 + (3,), np.float32)
        self.weight = np.zeros((self.cells,) * 3, np.float32)
        self._blocks: np.ndarray | None = None  # `_block_map`

    def half_extent_m(self) -> float:
        return 0.5 * self.cells * self.cell_m

    def contains(self, point_world: np.ndarray, margin_m: float = 0.0) -> bool:
        """Whether a point lies inside the grid, at least margin_m from its faces."""
        p = np.asarray(point_world, np.float64) - self.origin
        size = self.cells * self.cell_m
        return bool(np.all(p >= margin_m) and np.all(p <= size - margin_m))

    def update(
        self,
        depth_m: np.ndarray,
        colour_linear: np.ndarray,
        world_from_cam: np.ndarray,
        camera: PinholeCamera,
        stride: int = 2,
        carve_margin_m: float = 0.03,
    ) -> int:
        """Carve, then fuse one frame (depth (H, W) metres, 0 = none; colour (H, W, 3) linear).
        Returns the number of points fused."""
        self._blocks = None
        depth = np.ascontiguousarray(np.nan_to_num(depth_m, nan=0.0, posinf=0.0), np.float32)
        # the nearest depth about each pixel (3x3; 0 = unknown stays out of the minimum)
        far = np.where(depth > 0, depth, np.float32(np.inf))
        near = cv2.erode(far, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        near = np.where(np.isfinite(near), near, 0.0).astype(np.float32)
        _carve(
            self.weight,
            self.origin,
            self.cell_m,
            np.linalg.inv(world_from_cam),
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            near,
            carve_margin_m + 2.0 * self.cell_m,
        )
        return int(
            _fuse_points(
                depth,
                np.ascontiguousarray(colour_linear, np.float32),
                int(stride),
                np.asarray(world_from_cam, np.float64),
                camera.fx,
                camera.fy,
                camera.cx,
                camera.cy,
                self.origin,
                self.cell_m,
                self.colour,
                self.weight,
            )
        )

    def _block_map(self) -> np.ndarray:
        """Which blocks hold surface: made on the first march after an `update` (or after
        `weight` was edited and `invalidate` called)."""
        if self._blocks is None:
            nb = -(-self.cells // BLOCK)
            self._blocks = np.zeros((nb, nb, nb), np.bool_)
            _block_occupancy(self.weight, BLOCK, self._blocks)
        return self._blocks

    def invalidate(self) -> None:
        """Forget the block map (after editing `weight` by hand)."""
        self._blocks = None

    def occupied(self, point_world: np.ndarray) -> bool:
        """Whether the cell holding a point is surface (False outside the grid)."""
        i = np.floor((np.asarray(point_world, np.float64) - self.origin) / self.cell_m).astype(int)
        if np.any(i < 0) or np.any(i >= self.cells):
            return False
        return bool(self.weight[i[0], i[1], i[2]] > 0)

    def march(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First surface along each ray: (distance (K,) metres, inf = miss; colour (K, 3)
        float32 linear, 0 on a miss). origins (K, 3) or (3,), directions (K, 3), world."""
        d = np.ascontiguousarray(np.asarray(directions, np.float64).reshape(-1, 3))
        o = np.ascontiguousarray(np.broadcast_to(np.asarray(origins, np.float64), d.shape))
        t = np.full(len(d), np.inf)
        rgb = np.zeros((len(d), 3), np.float32)
        if len(d):
            blocks = self._block_map()
            _march_kernel(
                o, d, self.origin, self.cell_m, self.weight, blocks, BLOCK, self.colour, t, rgb
            )
        return t, rgb


__all__ = ["WEIGHT_CAP", "RoomGrid"]
