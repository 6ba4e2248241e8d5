"""Hard shadows of a compact light source, both ways, for the composite.

A compact source (compact_light.CompactSource: direction w, integrated luminance k,
angular radius r) lights a surface point x with normal n by k V(x) max(0, n . w), where
V(x) in [0, 1] is the fraction of the source's disc seen from x: `samples` rays towards
directions spread over the disc (a fixed, seeded pattern: the penumbra's width follows
r and the occluder's distance), each blocked or not by a mesh at any distance.

For the composite (rendering.DifferentialRenderer): a real pixel lit by the source loses
k max(0, n . w) (1 - V_virtual) of its irradiance where a virtual object blocks it, so its
colour is scaled by (E_rest + k cos V_virtual V_real) / (E_rest + k cos V_real); a virtual
pixel gains k cos V_virtual V_real (its own shadow and the real scene's). E_rest is the
rest of the light (the ambient SH's irradiance).
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import open3d.core as o3c

RAY_OFFSET_M = 0.01  # rays start this far along the normal (metres)
RAY_TNEAR_M = 0.002


def disc_directions(direction: np.ndarray, angular_radius_deg: float, samples: int) -> np.ndarray:
    """(S, 3) unit directions spread evenly over a disc of the given angular radius around
    `direction` (S = 1: the centre only). Deterministic (a Fibonacci spiral)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    if samples <= 1 or angular_radius_deg <= 0.0:
        return d[None]
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    i = np.arange(samples) + 0.5
    radius = math.tan(math.radians(angular_radius_deg)) * np.sqrt(i / samples)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    out = d + radius[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


class MeshOccluder:
    """Triangle meshes (world frame) that block rays, in an Open3D RaycastingScene."""

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]]):
        """meshes: (vertices (N, 3) metres, triangles (M, 3) indices) per mesh, world frame."""
        self._scene = o3d.t.geometry.RaycastingScene()
        self.empty = True
        for vertices, triangles in meshes:
            if len(triangles):
                self._scene.add_triangles(
                    o3c.Tensor(np.ascontiguousarray(vertices, np.float32)),
                    o3c.Tensor(np.ascontiguousarray(triangles).astype(np.uint32)),
                )
                self.empty = False

    def visibility(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        direction: np.ndarray,
        angular_radius_deg: float,
        samples: int = 8,
    ) -> np.ndarray:
        """(N,) fraction of the source's disc seen from each point (world frame; points
        (N, 3), normals (N, 3) unit; facing away from the source: 0 not tested, returns 1
        there so that a caller's cosine decides)."""
        n = len(points)
        if self.empty or n == 0:
            return np.ones(n)
        dirs = disc_directions(direction, angular_radius_deg, samples)
        origins = (points + RAY_OFFSET_M * normals).astype(np.float32)
        seen = np.zeros(n)
        for d in dirs:
            rays = np.empty((n, 6), np.float32)
            rays[:, :3] = origins
            rays[:, 3:] = d
            blocked = self._scene.test_occlusions(
                o3c.Tensor.from_numpy(rays), tnear=RAY_TNEAR_M, tfar=np.inf
            ).numpy()
            seen += ~blocked
        return seen / len(dirs)


def real_surface_factor(
    ambient_irradiance: np.ndarray,
    source_irradiance: np.ndarray,
    visible_virtual: np.ndarray,
    visible_real: np.ndarray,
) -> np.ndarray:
    """(N,) the factor that takes a real surface's observed colour to its colour with the
    virtual objects' shadow: (E + S V_v V_r) / (E + S V_r), with E the ambient irradiance,
    S = k max(0, n . w) the source's unshadowed irradiance, V_v, V_r the visibility of the
    source past the virtual and the real geometry. 1 where nothing changes."""
    e = np.maximum(ambient_irradiance, 0.0)
    s = np.maximum(source_irradiance, 0.0)
    before = e + s * visible_real
    after = e + s * visible_real * visible_virtual
    return np.where(before > 1e-12, after / np.maximum(before, 1e-12), 1.0)
