"""Hard shadows of a compact source (pipeline.sun_shadows): geometry against a known sun."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from arlight.pipeline.sun_shadows import MeshOccluder, disc_directions, real_surface_factor


def _box(centre: tuple[float, float, float], half: tuple[float, float, float]):
    """An axis-aligned box mesh (vertices, triangles), world frame."""
    c, h = np.asarray(centre), np.asarray(half)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h + c
    faces = [
        (0, 1, 3, 2),
        (4, 6, 7, 5),
        (0, 4, 5, 1),
        (2, 3, 7, 6),
        (0, 2, 6, 4),
        (1, 5, 7, 3),
    ]
    tris = [t for a, b, cc, d in faces for t in ((a, b, cc), (a, cc, d))]
    return corners.astype(np.float32), np.array(tris, np.int32)


def _sun(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])


def _ground(extent: float = 1.6, step: float = 0.005):
    g = np.arange(-extent, extent, step) + step / 2
    x, z = np.meshgrid(g, g)
    points = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    return points, normals


@pytest.mark.parametrize("elevation, azimuth", [(35.0, 60.0), (20.0, -135.0), (60.0, 10.0)])
def test_pole_shadow_direction_and_length(elevation: float, azimuth: float) -> None:
    """A 0.5 m pole on the ground under a sun: its shadow points away from the sun within
    2 degrees and is h / tan(elevation) long within 5 %."""
    height, half_width = 0.5, 0.01
    pole = MeshOccluder([_box((0.0, height / 2, 0.0), (half_width, height / 2, half_width))])
    sun = _sun(elevation, azimuth)
    points, normals = _ground()
    seen = pole.visibility(points, normals, sun, angular_radius_deg=0.27, samples=4)
    shadow = points[seen < 0.5]
    assert len(shadow) > 20
    away = -np.array([sun[0], sun[2]]) / np.hypot(sun[0], sun[2])
    flat = shadow[:, [0, 2]]
    along = flat @ away
    tip = flat[np.argmax(along)]
    direction_err = math.degrees(math.acos(np.clip(tip @ away / np.linalg.norm(tip), -1, 1)))
    assert direction_err < 2.0
    expected = height / math.tan(math.radians(elevation)) + half_width
    assert abs(along.max() - expected) / expected < 0.05
    # nothing in shadow on the sun's side of the pole
    assert along.min() > -2 * half_width - 0.01


def test_penumbra_widens_with_the_source() -> None:
    """A larger disc: more partly lit ground points (0 < V < 1) behind the same edge."""
    wall = MeshOccluder([_box((0.0, 0.5, 0.0), (0.6, 0.5, 0.01))])
    sun = _sun(40.0, 90.0)
    points, normals = _ground(extent=1.0, step=0.01)
    partial = []
    for radius in (0.27, 3.0):
        seen = wall.visibility(points, normals, sun, angular_radius_deg=radius, samples=16)
        partial.append(int(np.sum((seen > 0.0) & (seen < 1.0))))
    assert partial[1] > 3 * max(partial[0], 1)


def test_disc_directions_stay_within_the_disc() -> None:
    d = _sun(30.0, 45.0)
    dirs = disc_directions(d, 2.0, 32)
    angles = np.degrees(np.arccos(np.clip(dirs @ d, -1, 1)))
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert angles.max() <= 2.0 + 1e-6 and angles.mean() > 0.8
    assert np.allclose(disc_directions(d, 2.0, 1), d[None])


def test_real_surface_factor() -> None:
    ambient = np.array([1.0, 1.0, 1.0, 0.0])
    source = np.array([3.0, 3.0, 3.0, 0.0])
    visible_virtual = np.array([1.0, 0.0, 0.0, 0.0])
    visible_real = np.array([1.0, 1.0, 0.0, 1.0])
    f = real_surface_factor(ambient, source, visible_virtual, visible_real)
    # unshadowed: no change; virtual shadow on a lit surface: the ambient's share remains;
    # already in a real shadow: no change; no light at all: no change
    assert np.allclose(f, [1.0, 0.25, 1.0, 1.0])


def test_empty_occluder_sees_everything() -> None:
    points, normals = _ground(extent=0.1, step=0.05)
    assert np.all(MeshOccluder([]).visibility(points, normals, _sun(30, 0), 0.27) == 1.0)


# ------------------------------------------------------------------ in the composite
def _pole_scene(height: float, half_width: float):
    import open3d as o3d
    from test_rendering import SPHERE_ALBEDO

    from arlight.pipeline.virtual_scene import Material, VirtualScene, object_from_open3d

    box = o3d.geometry.TriangleMesh.create_box(2 * half_width, height, 2 * half_width)
    box.translate((-half_width, 0.0, -half_width))
    box.compute_vertex_normals()
    pole = object_from_open3d("pole", box, np.eye(4), Material((SPHERE_ALBEDO,) * 3))
    return VirtualScene((pole,))


@pytest.mark.parametrize("azimuth", [30.0, 150.0])
def test_virtual_pole_shadow_in_the_composite(azimuth: float) -> None:
    """A 0.4 m virtual pole on the real ground under a known sun (a compact source): the
    ground it darkens lies away from the sun within 2 degrees and reaches h / tan(elevation)
    within 5 %; the same light as SH alone (the SSDO differential) casts no such shadow."""
    from test_rendering import UP, darkened, frame_inputs, ground_view

    from arlight.pipeline import sh
    from arlight.pipeline.config import Config
    from arlight.pipeline.rendering import DifferentialRenderer
    from arlight.pipeline.sun_shadows import SourceLight

    height, half_width, elevation = 0.4, 0.01, 35.0
    view = ground_view(320, 240, distance_m=1.6, tilt_deg=70.0)
    sun = _sun(elevation, azimuth)
    ambient = np.zeros(16)
    ambient[0] = 0.1 / sh.sh_basis(UP, 1)[0]
    total = ambient + sh.directional_light(sun, 2.0, 4)
    renderer = DifferentialRenderer(_pole_scene(height, half_width), view.camera, Config())
    inputs = frame_inputs(view, total)  # the real ground as lit by ambient + sun
    with_source = dataclasses.replace(
        inputs, light_sh=ambient, sources=[SourceLight(sun, 2.0, np.ones(3), 0.27)]
    )
    out = renderer.render(with_source)
    dark = darkened(with_source, out, 0.3)
    vv, uu = np.nonzero(dark)
    # rays_world have camera z = 1: a pixel's point is its ray times its depth
    points = view.world_from_cam[:3, 3] + view.rays_world[vv, uu] * view.depth_m[vv, uu, None]
    away = -np.array([sun[0], sun[2]]) / np.hypot(sun[0], sun[2])
    flat = points[:, [0, 2]]
    along = flat @ away
    tip = flat[np.argmax(along)]
    assert math.degrees(math.acos(np.clip(tip @ away / np.linalg.norm(tip), -1, 1))) < 2.0
    expected = height / math.tan(math.radians(elevation)) + half_width
    assert abs(along.max() - expected) / expected < 0.05
    # the SH alone (4 bands of the same light): nothing darkened at the shadow's far half
    sh_only = renderer.render(inputs)
    far = darkened(inputs, sh_only, 0.3)
    vv, uu = np.nonzero(far)
    if len(vv):
        p = view.world_from_cam[:3, 3] + view.rays_world[vv, uu] * view.depth_m[vv, uu, None]
        assert (p[:, [0, 2]] @ away).max() < 0.5 * expected
