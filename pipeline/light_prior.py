"""A prior over the distant light learned from HDR environment maps.

The statistics of natural illumination in the SH the fit solves for (bands 0..3, arlight's
basis), as a Gaussian over the coefficients divided by band 0 (exposure and albedo make the
scale unknowable), with the rotation about "up" marginalised: every map counts at 36
headings, equally weighted. What is modelled is the light a scene on a ground receives: the
map's upper hemisphere, and below the horizon the glow of a ground of albedo 0.3 lit by it.

The per-map moments ship in ``light_prior_maps.json`` (made by
``python -m arlight.synth.light_prior``, which lists the maps that went in); pooling them
while leaving maps out is exact, so a prior is judged on maps it never saw (`exclude`).

In the fit the prior is the quadratic penalty (A l)^T Q (A l), A l = l_{1..} - l_0 mu_{1..}:
zero-centred, so the solver's existing `prior` argument carries it (pipeline.light_estimation).
"""

from __future__ import annotations

import functools
import json
from importlib import resources

import numpy as np

from arlight.pipeline import sh

PRIOR_FILE = "light_prior_maps.json"
RIDGE = 1e-4  # added to the covariance's diagonal (units of band 0 squared)
Y_UP = np.array([0.0, 1.0, 0.0])


@functools.lru_cache(maxsize=1)
def map_moments() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """map name -> (mean (16,), second moment (16, 16)) of c / c_0, canonical frame (+y up)."""
    doc = json.loads(resources.files("arlight.pipeline").joinpath(PRIOR_FILE).read_text())
    return {
        name: (np.asarray(m["mean"], float), np.asarray(m["second_moment"], float))
        for name, m in doc["maps"].items()
    }


def _key(name: str) -> str:
    return name[:-3] if name.endswith("_1k") else name


@functools.lru_cache(maxsize=64)
def pooled(exclude: frozenset[str] = frozenset()) -> tuple[np.ndarray, np.ndarray]:
    """(mean (16,), covariance (16, 16)) over the maps not in `exclude` (names with or
    without the _1k suffix), canonical frame."""
    left_out = {_key(n) for n in exclude}
    moments = [m for name, m in map_moments().items() if _key(name) not in left_out]
    if not moments:
        raise ValueError("light_prior_exclude leaves no map for the light prior")
    mean = np.mean([m[0] for m in moments], axis=0)
    second = np.mean([m[1] for m in moments], axis=0)
    return mean, second - np.outer(mean, mean)


def _rotation_taking_y_to(up: np.ndarray) -> np.ndarray:
    """A rotation R (3, 3) with R @ (0, 1, 0) = up (the prior is symmetric about +y)."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    axis = np.cross(Y_UP, u)
    s, c = float(np.linalg.norm(axis)), float(Y_UP @ u)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def prior_matrix(up: np.ndarray, bands: int, exclude: frozenset[str] = frozenset()) -> np.ndarray:
    """P (n, n), n = bands^2, with l^T P l = (A l)^T Q (A l) in the frame where `up` is up:
    A l = l_{1..n-1} - l_0 mu_{1..n-1}, Q the inverse covariance of those coefficients."""
    n = bands * bands
    if n < 4:
        return np.zeros((n, n))
    mean, cov = pooled(frozenset(exclude))
    m = sh.rotation_matrix(_rotation_taking_y_to(up), 4)
    mean_w, cov_w = m @ mean, m @ cov @ m.T
    mu, c = mean_w[:n], cov_w[1:n, 1:n] + RIDGE * np.eye(n - 1)
    a = np.zeros((n - 1, n))
    a[:, 0] = -mu[1:] / mu[0]
    a[:, 1:] = np.eye(n - 1)
    return a.T @ np.linalg.inv(c) @ a
