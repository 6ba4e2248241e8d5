"""Which points lie within a distance of a triangle mesh, with few exact distance queries.

The renderer asks, for a few thousand grid points a frame, which lie within rt_radius_m of a
virtual object (`rendering`): only from those can a sample meet it. The exact distance to the
triangles (Open3D's `compute_distance`) costs about 2 microseconds a point. Points sampled
over the surfaces, no surface point farther than `cover_m` from one of them, bound that
distance cheaply through a k-d tree: the distance d_s to the nearest sample and the exact
distance d satisfy d <= d_s <= d + cover_m. So d_s <= reach means within reach,
d_s - cover_m > reach means not, and only the points in between (a shell `cover_m` thick)
need the exact query. The answer is the exact one.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

MAX_SAMPLES = 200_000  # the sampling's spacing grows until a scene fits in this many points


def surface_samples(
    vertices: np.ndarray, triangles: np.ndarray, spacing_m: float
) -> tuple[np.ndarray, float]:
    """Points on the triangles (vertices (V, 3), triangles (T, 3)) and their cover: every
    surface point lies within `cover` metres of one. Each triangle is cut into n x n
    similar triangles (n = its longest edge over spacing_m, rounded up) whose corners are the
    samples; a point of a small triangle is within its longest edge of a corner."""
    v = np.asarray(vertices, np.float64)
    tri = np.asarray(triangles, np.int64)
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    longest = np.max(
        np.stack(
            [
                np.linalg.norm(b - a, axis=1),
                np.linalg.norm(c - b, axis=1),
                np.linalg.norm(a - c, axis=1),
            ]
        ),
        axis=0,
    )
    cuts = np.maximum(1, np.ceil(longest / spacing_m).astype(np.int64))
    points = [v]
    for n in np.unique(cuts[cuts > 1]):
        sel = cuts == n
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j) <= n
        u, w = i[keep] / n, j[keep] / n  # barycentric weights of b and c
        pa, pb, pc = a[sel], b[sel], c[sel]
        grid = (
            pa[:, None]
            + u[None, :, None] * (pb - pa)[:, None]
            + w[None, :, None] * (pc - pa)[:, None]
        )
        points.append(grid.reshape(-1, 3))
    cover = float(np.max(longest / cuts)) if len(longest) else 0.0
    return np.concatenate(points), cover


class WithinReach:
    """`within(points, reach)` for a fixed set of meshes (world frame), exact, with the exact
    `distance` (points (K, 3) -> (K,) metres) asked only where the samples' bound is open."""

    def __init__(
        self,
        meshes: list[tuple[np.ndarray, np.ndarray]],
        distance: Callable[[np.ndarray], np.ndarray],
        spacing_m: float = 0.01,
    ):
        self._distance = distance
        self.exact_queries = 0  # points the exact distance was asked for (for tests)
        spacing = spacing_m
        while True:
            parts = [surface_samples(v, t, spacing) for v, t in meshes if len(t)]
            count = sum(len(p) for p, _ in parts)
            if count <= MAX_SAMPLES or not parts:
                break
            spacing *= math.sqrt(count / MAX_SAMPLES) * 1.1
        self.cover_m = max((c for _, c in parts), default=0.0)
        samples = np.concatenate([p for p, _ in parts]) if parts else np.zeros((0, 3))
        self._tree = cKDTree(samples) if len(samples) else None

    def within(self, points: np.ndarray, reach: float) -> np.ndarray:
        """(K,) bool: whether each world point (K, 3) lies within `reach` metres of a
        surface, the same answer as the exact distance gives."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if self._tree is None or not len(p):
            return np.zeros(len(p), bool)
        bound, _ = self._tree.query(p, distance_upper_bound=reach + self.cover_m + 1e-9)
        inside = bound <= reach
        open_ = ~inside & (bound - self.cover_m <= reach)
        if np.any(open_):
            self.exact_queries += int(open_.sum())
            inside[open_] = self._distance(p[open_]) <= reach
        return inside


__all__ = ["MAX_SAMPLES", "WithinReach", "surface_samples"]
