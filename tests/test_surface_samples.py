"""`surface_samples`: which points lie within reach of the virtual objects, exactly, with
few exact distance queries."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from arlight.pipeline.surface_samples import WithinReach, surface_samples
from arlight.pipeline.virtual_gbuffer import VirtualRaycaster
from arlight.pipeline.virtual_scene import Material, VirtualScene, object_from_open3d


def _scene() -> VirtualRaycaster:
    """A sphere of radius 0.2 m on the origin and a 1 m x 0.1 m x 0.4 m box beside it (large
    faces: two triangles each)."""
    ball = o3d.geometry.TriangleMesh.create_sphere(0.2, resolution=20)
    box = o3d.geometry.TriangleMesh.create_box(1.0, 0.1, 0.4)
    box.translate((0.3, -0.05, -0.2))
    objects = [
        object_from_open3d(name, mesh, np.eye(4), Material((0.5,) * 3))
        for name, mesh in (("ball", ball), ("box", box))
    ]
    return VirtualRaycaster(VirtualScene(tuple(objects)))


def test_every_surface_point_is_within_the_cover_of_a_sample():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 0.5, 0]], float)
    samples, cover = surface_samples(vertices, np.array([[0, 1, 2]]), 0.05)
    assert cover <= 0.05
    rng = np.random.default_rng(1)
    u, w = rng.uniform(size=(2, 2000))
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    points = u[:, None] * vertices[1] + w[:, None] * vertices[2]
    nearest = np.min(np.linalg.norm(points[:, None] - samples[None], axis=2), axis=1)
    assert nearest.max() <= cover


@pytest.mark.parametrize("reach", [0.02, 0.1, 0.5])
def test_the_exact_answer_with_few_exact_queries(reach):
    raycaster = _scene()
    reach_test = WithinReach(
        [(o.world_vertices(), o.triangles) for o in raycaster.scene.objects],
        raycaster.distance_to_objects,
    )
    points = np.random.default_rng(0).uniform((-1.0, -0.8, -1.0), (1.8, 0.8, 1.0), (20000, 3))
    exact = raycaster.distance_to_objects(points) <= reach
    got = reach_test.within(points, reach)
    np.testing.assert_array_equal(got, exact)
    assert 0 < exact.sum() < len(points)  # the boundary runs through the points
    assert reach_test.exact_queries < 0.1 * len(points)


def test_nothing_is_within_reach_of_no_surface():
    reach_test = WithinReach([], lambda p: np.full(len(p), np.inf))
    assert not reach_test.within(np.zeros((3, 3)), 1.0).any()
