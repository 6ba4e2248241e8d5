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
    before = source * visible_real
    f = real_surface_factor(ambient, before, before * visible_virtual)
    # unshadowed: no change; virtual shadow on a lit surface: the ambient's share remains;
    # already in a real shadow: no change; no light at all: no change
    assert np.allclose(f, [1.0, 0.25, 1.0, 1.0])


def test_the_ambient_ratio_weighs_only_the_ambient_share() -> None:
    # SSDO halves the ambient near an object; in the sun it halves only the ambient's share
    # (1 of 4), in a real shadow all of the light, and in the object's shadow both go
    ambient, sun = np.full(3, 1.0), np.array([3.0, 0.0, 3.0])
    f = real_surface_factor(ambient, sun, sun * np.array([1.0, 1.0, 0.0]), 0.5)
    assert np.allclose(f, [(0.5 + 3.0) / 4.0, 0.5, 0.5 / 4.0])


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


def test_the_objects_ambient_occlusion_does_not_dim_the_sunlit_ground() -> None:
    """A 0.2 m wide virtual box on the ground, lit 95 % by a sun: the ground beside it on
    the sun's side keeps its sunlight, so SSDO's occlusion of the sky there may take only
    the ambient's share (at most 5 %); in the box's shadow only that share remains."""
    from test_rendering import UP, frame_inputs, ground_view, luminance

    from arlight.pipeline import sh
    from arlight.pipeline.color import srgb_to_linear
    from arlight.pipeline.config import Config
    from arlight.pipeline.rendering import DifferentialRenderer
    from arlight.pipeline.sun_shadows import SourceLight

    half, elevation, azimuth = 0.1, 35.0, 0.0
    view = ground_view(320, 240, distance_m=1.2, tilt_deg=60.0)
    sun = _sun(elevation, azimuth)
    ambient = np.zeros(16)
    ambient[0] = 0.1 / sh.sh_basis(UP, 1)[0]  # radiance 0.1: irradiance 0.1 pi on the ground
    source = 19.0 * 0.1 * math.pi / math.sin(math.radians(elevation))  # 95 % of its light
    renderer = DifferentialRenderer(_pole_scene(0.2, half), view.camera, Config())
    inputs = frame_inputs(view, ambient + sh.directional_light(sun, source, 4))
    out = renderer.render(
        dataclasses.replace(
            inputs, light_sh=ambient, sources=[SourceLight(sun, source, np.ones(3), 0.27)]
        )
    )
    ratio = luminance(srgb_to_linear(out.composite)) / np.maximum(
        luminance(inputs.color_linear), 1e-9
    )
    points = view.world_from_cam[:3, 3] + view.rays_world * view.depth_m[..., None]
    x, z = points[..., 0], points[..., 2]
    beside = ~out.virtual_mask & (view.depth_m > 0) & (np.abs(z) < 0.05)
    toward = -np.array([sun[0], sun[2]]) / np.hypot(sun[0], sun[2])  # where the shadow falls
    sunny_side = (
        beside & (x * toward[0] < 0) & (np.abs(x) > half + 0.01) & (np.abs(x) < half + 0.04)
    )
    shadow = beside & (x * toward[0] > 0) & (np.abs(x) > half + 0.03) & (np.abs(x) < half + 0.08)
    assert sunny_side.sum() > 20 and shadow.sum() > 20
    assert np.median(ratio[sunny_side]) > 0.96
    assert np.median(ratio[shadow]) < 0.08


def test_the_indirect_change_takes_the_albedo_from_all_the_light() -> None:
    """A sunlit grey surface (albedo 0.5: observed 0.5 / pi (E + S)) read against the ambient
    alone looks brighter than white and was clamped at 1 / pi; against all its light it is
    0.5 / pi again, so the bounce it gets or loses is scaled by 0.5."""
    from arlight.pipeline.sun_shadows import _indirect_with_source

    ambient, source = np.array([1.0, 1.0]), np.array([3.0, 0.0])
    observed = 0.5 / math.pi * (ambient + source)[:, None] * np.ones(3)
    delta = np.full((2, 3), -0.02)
    out = _indirect_with_source(delta, observed, ambient, source, np.ones(3))
    assert np.allclose(out[0], -0.02 * 0.5)  # was read as 1 / pi, is 0.5 / pi
    assert np.allclose(out[1], -0.02)  # no source: as the SH renderer read it


@pytest.mark.parametrize("with_change", [True, False])
def test_the_real_pixels_kernel_is_the_two_definitions(with_change: bool) -> None:
    """`_shade_real_pixels` (one pixel at a time) gives the codes and the changed mask of
    `real_surface_factor` and `_indirect_with_source` over gathered arrays, bit for bit:
    pixels inside and outside the SH part's rectangle, unlit ones, sunlit bright ones."""
    from arlight.pipeline.srgb_encoding import TABLE_BASE, TABLE_NEXT, linear_to_srgb_u8
    from arlight.pipeline.sun_shadows import _indirect_with_source, _shade_real_pixels

    rng = np.random.default_rng(3)
    h, w, n = 40, 50, 600
    colour = rng.uniform(0.0, 0.6, (h, w, 3)).astype(np.float32)
    flat = rng.choice(h * w, n, replace=False)
    rows, cols = flat // w, flat % w
    ambient = rng.uniform(-0.1, 2.0, n)
    ambient[:20] = 0.0  # no light at all on some
    before = rng.uniform(0.0, 3.0, n) * (rng.random(n) < 0.7)
    after = before * rng.uniform(0.0, 1.0, n)
    origin, ratio = (5, 7), rng.uniform(0.5, 1.2, (20, 30))
    ratio[ratio > 1.1] = 1.0
    delta = rng.normal(0.0, 0.01, (20, 30, 3)) * (rng.random((20, 30, 1)) < 0.5)
    if not with_change:
        ratio, delta = np.ones((0, 0)), np.zeros((0, 0, 3))
    rgb = np.array([1.1, 1.0, 0.8])
    # the definitions, over gathered arrays
    r, c = rows - origin[0], cols - origin[1]
    inside = (r >= 0) & (r < ratio.shape[0]) & (c >= 0) & (c < ratio.shape[1])
    rho, added = np.ones(n), np.zeros((n, 3))
    rho[inside], added[inside] = ratio[r[inside], c[inside]], delta[r[inside], c[inside]]
    factor = real_surface_factor(ambient, before, after, rho)
    observed = colour[rows, cols].astype(np.float64)
    linear = observed * factor[:, None] + _indirect_with_source(
        added, observed, ambient, before, rgb
    )
    composite = np.zeros((h, w, 3), np.uint8)
    changed = np.zeros((h, w), bool)
    _shade_real_pixels(
        rows, cols, ambient, before, after, origin, ratio, delta, colour, rgb, composite,
        changed, TABLE_BASE, TABLE_NEXT
    )  # fmt: skip
    np.testing.assert_array_equal(composite[rows, cols], linear_to_srgb_u8(linear))
    expected = (factor != 1.0) | np.any(added != 0.0, axis=1)
    np.testing.assert_array_equal(changed[rows, cols], expected)
    assert 0 < expected.sum() < n and changed.sum() == expected.sum()


def test_real_pixels_in_one_pass_are_the_masks_expression() -> None:
    """`_real_pixels` is ~virtual & (z > 0) & any_nonzero(normals), NaN normals counting
    as normals and NaN depth as none."""
    from arlight.pipeline.channels import any_nonzero
    from arlight.pipeline.sun_shadows import _real_pixels

    rng = np.random.default_rng(4)
    virtual = rng.random((30, 40)) < 0.2
    points = rng.normal(0.5, 1.0, (30, 40, 3)).astype(np.float32)
    normals = rng.normal(0.0, 1.0, (30, 40, 3)).astype(np.float32)
    normals[rng.random((30, 40)) < 0.3] = 0.0
    normals[3, 4, 1], points[5, 6, 2] = np.nan, np.nan
    out = np.empty((30, 40), bool)
    _real_pixels(virtual, points, normals, out)
    expected = ~virtual & (points[..., 2] > 0) & any_nonzero(normals)
    np.testing.assert_array_equal(out, expected)
    assert 0 < out.sum() < out.size


def test_the_objects_pixels_take_the_sh_parts_linear_colour() -> None:
    """Given the SH part's linear colour of the virtual pixels, `apply` adds the source's
    light to it and encodes once; without it, it reads the composite's 8 bits back."""
    from arlight.pipeline.srgb_encoding import linear_to_srgb_u8
    from arlight.pipeline.sun_shadows import CompactSourceShading, SourceLight

    h, w = 12, 16
    shading = CompactSourceShading([_box((0.0, 0.0, 5.0), (0.2, 0.2, 0.2))])
    virtual = np.zeros((h, w), bool)
    virtual[4:8, 5:9] = True
    normals = np.zeros((h, w, 3), np.float32)
    normals[virtual] = (0.0, 0.0, -1.0)  # facing the camera and the source
    points = np.zeros((h, w, 3), np.float32)
    points[virtual] = (0.0, 0.0, 4.0)  # in front of the box: nothing blocks them
    albedo = np.full((h, w, 3), 0.5, np.float32)
    source = SourceLight(np.array([0.0, 0.0, -1.0]), 0.3, np.ones(3), 0.5)
    linear = np.full((int(virtual.sum()), 3), 0.2)
    for given in (linear, None):
        composite = np.zeros((h, w, 3), np.uint8)
        changed = shading.apply(
            composite, virtual, normals, albedo, points, np.zeros((h, w, 3), np.float32),
            np.zeros((h, w, 3), np.float32), np.eye(4), np.zeros(9), np.ones(3), [source],
            None, np.zeros((h, w, 3), np.float32), None, given,
        )  # fmt: skip
        base = 0.2 if given is not None else 0.0
        expected = linear_to_srgb_u8(np.array([base + 0.5 / math.pi * 0.3]))[0]
        assert np.all(composite[virtual] == expected) and np.all(composite[~virtual] == 0)
        assert np.array_equal(changed, virtual)


def test_a_mirror_takes_the_source_only_from_what_it_reflects() -> None:
    """A mirror pole and a diffuse pole under a sun, a panorama reflected: the source adds
    its diffuse light to the diffuse pole's pixels and none to the mirror's, whose
    reflection holds the light already (it was lit twice: the mirror drew the source's
    albedo / pi S on top of its reflection)."""
    import open3d as o3d
    from test_rendering import UP, frame_inputs, ground_view

    from arlight.pipeline import sh
    from arlight.pipeline.config import Config
    from arlight.pipeline.glossy import mip_pyramid
    from arlight.pipeline.rendering import DifferentialRenderer, EnvironmentMap
    from arlight.pipeline.sun_shadows import SourceLight
    from arlight.pipeline.virtual_scene import Material, VirtualScene, object_from_open3d

    objects = []
    for name, x, material in (
        ("mirror", -0.15, Material((0.9,) * 3, mirror=True)),
        ("diffuse", 0.15, Material((0.6,) * 3)),
    ):
        box = o3d.geometry.TriangleMesh.create_box(0.1, 0.3, 0.1)
        box.translate((x - 0.05, 0.0, -0.05))
        box.compute_vertex_normals()
        objects.append(object_from_open3d(name, box, np.eye(4), material))
    view = ground_view(320, 240, distance_m=1.2, tilt_deg=40.0)
    sun = _sun(35.0, 90.0)  # towards the camera's side (+z): the poles' fronts face it
    ambient = np.zeros(16)
    ambient[0] = 0.1 / sh.sh_basis(UP, 1)[0]
    renderer = DifferentialRenderer(VirtualScene(tuple(objects)), view.camera, Config())
    panorama = EnvironmentMap(mip_pyramid(np.full((16, 32, 3), 0.1, np.float32)), np.eye(3))
    inputs = dataclasses.replace(
        frame_inputs(view, ambient + sh.directional_light(sun, 2.0, 4)),
        light_sh=ambient,
        environment=panorama,
    )
    without = renderer.render(inputs)
    lit = renderer.render(
        dataclasses.replace(inputs, sources=[SourceLight(sun, 2.0, np.ones(3), 0.27)])
    )
    index = without.gbuffer.object_index
    mirror, diffuse = index == 0, index == 1
    assert mirror.sum() > 200 and diffuse.sum() > 200
    gain = lit.composite.astype(int) - without.composite.astype(int)
    assert np.all(gain[mirror] == 0)
    assert np.median(gain[diffuse]) > 10


def test_rays_that_miss_the_bounding_sphere_are_never_blocked() -> None:
    """`may_block` is conservative: every ground point a pole's disc of rays reaches is
    kept, for a point sun and a wide disc, and most of the ground is left out."""
    pole = MeshOccluder([_box((0.0, 0.25, 0.0), (0.01, 0.25, 0.01))])
    points, normals = _ground(extent=1.0, step=0.01)
    for radius in (0.27, 5.0):
        sun = _sun(35.0, 60.0)
        seen = pole.visibility(points, normals, sun, angular_radius_deg=radius, samples=16)
        may = pole.may_block(points, sun, radius)
        assert np.all(may[seen < 1.0])
        assert may.mean() < 0.25


def test_the_composite_is_the_same_without_the_bounding_sphere(monkeypatch) -> None:
    """The real pixels tested for the objects' shadow are culled by the objects' bounding
    sphere; with every pixel tested instead the composite is identical, bit for bit."""
    from test_rendering import UP, frame_inputs, ground_view

    from arlight.pipeline import sh
    from arlight.pipeline.config import Config
    from arlight.pipeline.rendering import DifferentialRenderer
    from arlight.pipeline.sun_shadows import SourceLight

    view = ground_view(320, 240, distance_m=1.6, tilt_deg=60.0)
    sun = _sun(30.0, 120.0)
    ambient = np.zeros(16)
    ambient[0] = 0.1 / sh.sh_basis(UP, 1)[0]
    renderer = DifferentialRenderer(_pole_scene(0.3, 0.05), view.camera, Config())
    inputs = dataclasses.replace(
        frame_inputs(view, ambient + sh.directional_light(sun, 2.0, 4)),
        light_sh=ambient,
        sources=[SourceLight(sun, 2.0, np.ones(3), 3.0)],
    )
    culled = renderer.render(inputs).composite.copy()
    assert np.any(culled != renderer.render(dataclasses.replace(inputs, sources=[])).composite)
    monkeypatch.setattr(
        MeshOccluder, "may_block", lambda self, points, *args, **kw: np.ones(len(points), bool)
    )
    np.testing.assert_array_equal(renderer.render(inputs).composite, culled)
