"""The radiance transfer's sampling pattern (section 5.1, eq. 9 of seeds/000): the N jittered
directions, the per-2x2-block sample radii (interleaved sampling) and the visibility
threshold chi from the directions' spherical Delaunay neighbours."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from arlight.pipeline import sh
from arlight.pipeline.config import TransferParams, VisibilityRamp


@dataclass(frozen=True)
class SamplingPattern:
    """Directions (N, 3) unit, camera frame; radii (2, 2, N, steps) metres; chi of eq. 9."""

    directions: np.ndarray
    radii: np.ndarray
    chi: float


def jittered_directions(n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` unit directions: a Fibonacci lattice with each point jittered within its cell."""
    base = sh.fibonacci_sphere(n)
    cell = math.sqrt(4.0 * math.pi / n)  # typical neighbour spacing, radians
    jitter = rng.normal(scale=0.25 * cell, size=(n, 3))
    jitter -= (jitter * base).sum(axis=1, keepdims=True) * base  # tangent to the sphere
    d = base + jitter
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def visibility_threshold(directions: np.ndarray) -> float:
    """chi of eq. 9: cos of half the median angle between neighbours of the spherical
    Delaunay triangulation (the convex hull of points on the unit sphere)."""
    hull = ConvexHull(directions)
    edges = set()
    for a, b, c in hull.simplices:
        for i, j in ((a, b), (b, c), (a, c)):
            edges.add((min(i, j), max(i, j)))
    idx = np.array(sorted(edges))
    cosines = np.clip((directions[idx[:, 0]] * directions[idx[:, 1]]).sum(axis=1), -1.0, 1.0)
    return float(math.cos(np.median(np.arccos(cosines)) / 2.0))


def make_sampling_pattern(params: TransferParams, seed: int = 0) -> SamplingPattern:
    """The N jittered directions, the sample radii and chi (eq. 9), seeded by `seed`."""
    rng = np.random.default_rng(seed)
    dirs = jittered_directions(params.rt_directions, rng)
    steps = params.rt_steps
    # one random distance per direction and 2x2 block position; with several steps per
    # direction the distances are stratified in (0, radius]
    u = rng.random((2, 2, params.rt_directions, steps))
    radii = (np.arange(steps) + u) / steps * params.rt_radius_m
    return SamplingPattern(dirs, radii.astype(np.float64), visibility_threshold(dirs))


def visibility_ramp(pattern: SamplingPattern, params: TransferParams) -> float:
    """The threshold c of K = min(c, 1 - t.w) / c: chi as printed in eq. 8 ("paper"), or
    1 - chi so K ramps over half the neighbour angle ("half")."""
    if params.rt_visibility_ramp is VisibilityRamp.PAPER:
        return pattern.chi
    return 1.0 - pattern.chi
