"""Compact light sources found from the shadows the scene casts (pipeline.compact_light)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arlight.core.camera import PinholeCamera
from arlight.core.frames import Confidence
from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh
from arlight.pipeline.compact_light import (
    ShadowTester,
    candidate_directions,
    fit_compact_source,
    refine_steps,
    shadow_edge,
    source_confidence,
)
from arlight.pipeline.light_confidence import MIN_FACTOR
from arlight.pipeline.light_estimation import penalty_matrix
from arlight.pipeline.object_space_transfer import OcclusionScene, SurfaceMesh

UP = np.array([0.0, 1.0, 0.0])


def _box(centre, half):
    c, h = np.asarray(centre, float), np.asarray(half, float)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h + c
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, cc, d in quads for t in ((a, b, cc), (a, cc, d))]
    return corners.astype(np.float32), np.array(tris, np.int32)


def _scene():
    """Ground points around two boxes (the casters), their world normals, and the boxes'
    mesh as the reconstruction."""
    boxes = [_box((0.0, 0.15, 0.0), (0.1, 0.15, 0.1)), _box((0.5, 0.1, -0.3), (0.08, 0.1, 0.08))]
    vertices = np.concatenate([boxes[0][0], boxes[1][0]])
    triangles = np.concatenate([boxes[0][1], boxes[1][1] + len(boxes[0][0])])
    rng = np.random.default_rng(1)
    xz = rng.uniform(-1.0, 1.0, (6000, 2))
    inside = (np.abs(xz[:, 0]) < 0.11) & (np.abs(xz[:, 1]) < 0.11)
    xz = xz[~inside]
    points = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    normals = np.tile(UP, (len(points), 1))
    return points, normals, OcclusionScene(SurfaceMesh(vertices, triangles, in_world=True))


def _observe(points, normals, scene, sun, sun_power, ambient):
    """Luminance of a white Lambertian ground: ambient SH irradiance plus the sun's, shadowed."""
    tester = ShadowTester([(scene, np.eye(4))], points, normals)
    sun_term = tester.shading(sun[None])[:, 0] * sun_power if sun_power else 0.0
    irr = sh.evaluate(sh.irradiance_from_radiance(ambient), normals)
    return irr + sun_term


def _fit(points, normals, scene, lum, min_edge_step=0.0, max_sources=1, min_elevation_deg=0.0):
    bands = 3
    per_coeff = np.repeat(sh.lambert_band_factors(bands), [2 * l + 1 for l in range(bands)])
    design = sh.sh_basis(normals, bands) * per_coeff  # unoccluded transfer
    tester = ShadowTester([(scene, np.eye(4))], points, normals)
    ones = np.ones(len(lum))
    return fit_compact_source(
        design,
        ones,
        ones,
        lum,
        None,
        penalty_matrix(bands, 4e-3, None, False),
        bands,
        tester,
        UP,
        search_samples=3000,
        min_edge_step=min_edge_step,
        max_sources=max_sources,
        min_elevation_deg=min_elevation_deg,
    )


def _sun(elevation_deg, azimuth_deg):
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])


def _ambient():
    a = np.zeros(9)
    a[0] = 0.3 / sh.sh_basis(UP, 1)[0]
    return a


@pytest.mark.parametrize("elevation, azimuth", [(35.0, 20.0), (55.0, -120.0), (20.0, 200.0)])
def test_a_sun_is_found_where_the_shadows_say(elevation, azimuth):
    points, normals, scene = _scene()
    sun = _sun(elevation, azimuth)
    lum = _observe(points, normals, scene, sun, 2.0, _ambient())
    fit = _fit(points, normals, scene, lum)
    assert len(fit.sources) == 1, fit.reason
    source = fit.sources[0]
    assert angular_error_deg(source.direction, sun) < 3.0
    assert source.intensity == pytest.approx(2.0, rel=0.15)
    assert source.share > 0.6
    assert "1 compact source" in fit.reason


def test_a_source_low_over_the_horizon_is_found_but_not_kept():
    """`compact_min_elevation_deg` (20 in every preset): a 12-degree light is found where its
    shadows say, but not kept (in rooms such sources were walls and windows); the reason
    says why, and a 35-degree sun is still kept."""
    points, normals, scene = _scene()
    low = _sun(12.0, 40.0)
    lum = _observe(points, normals, scene, low, 2.0, _ambient())
    assert len(_fit(points, normals, scene, lum).sources) == 1
    gated = _fit(points, normals, scene, lum, min_elevation_deg=20.0)
    assert gated.sources == ()
    assert angular_error_deg(gated.direction, low) < 3.0
    assert "an elevation of at least 20 deg" in gated.reason
    high = _observe(points, normals, scene, _sun(35.0, 40.0), 2.0, _ambient())
    assert len(_fit(points, normals, scene, high, min_elevation_deg=20.0).sources) == 1


def test_no_source_under_an_overcast_sky():
    """Ambient light only: no direction's shadow explains anything; the reason says so."""
    points, normals, scene = _scene()
    ambient = _ambient()
    ambient[2] = 0.1  # a sky brighter above than at the horizon (band 1 along y)
    lum = _observe(points, normals, scene, UP, 0.0, ambient)
    lum = lum * np.random.default_rng(2).normal(1.0, 0.02, len(lum))  # sensor noise
    fit = _fit(points, normals, scene, lum)
    assert fit.sources == ()
    assert fit.reason.startswith("none")


def test_the_image_steps_across_a_real_shadow_edge_and_not_across_smooth_shading():
    """A sun's hard shadow makes a step across the edge the reconstruction predicts
    (ln((ambient + sun) / ambient) on the white ground); the same predicted edge drawn over
    smooth shading (a soft light's gradual darkening) shows about none."""
    points, normals, scene = _scene()
    ambient = _ambient()
    sun = _sun(35.0, 20.0)
    column = ShadowTester([(scene, np.eye(4))], points, normals).shading(sun[None])[:, 0]
    ones = np.ones(len(points))
    hard = _observe(points, normals, scene, sun, 2.0, ambient)
    expected = math.log((0.3 * math.pi + 2.0 * math.sin(math.radians(35.0))) / (0.3 * math.pi))
    assert shadow_edge(points, normals, ones, hard, column, sun) == pytest.approx(expected, rel=0.1)
    # darker towards the boxes, smoothly (half as bright at 1 m)
    smooth = 0.3 * math.pi * (0.5 + 0.5 * np.minimum(np.hypot(points[:, 0], points[:, 2]), 1.0))
    assert abs(shadow_edge(points, normals, ones, smooth, column, sun)) < 0.03
    # no pixels on the edge of another material: nothing to compare
    other = np.where(column > 0.0, 1.0, 2.0)
    assert shadow_edge(points, normals, other, hard, column, sun) == 0.0


def test_a_source_without_a_step_at_its_shadow_edge_is_dropped():
    points, normals, scene = _scene()
    lum = _observe(points, normals, scene, _sun(35.0, 20.0), 2.0, _ambient())
    kept = _fit(points, normals, scene, lum, min_edge_step=0.03)
    assert len(kept.sources) == 1 and "steps by" in kept.reason
    dropped = _fit(points, normals, scene, lum, min_edge_step=2.0 * kept.edge_step)
    assert dropped.sources == ()
    assert "across its shadow's edge (needs" in dropped.reason


def test_candidates_cover_the_upper_hemisphere_only():
    dirs = candidate_directions(UP, 256)
    assert len(dirs) > 200 and np.all(dirs @ UP > 0.0)
    # every direction above 10 degrees has a candidate within 9 degrees
    probe = sh.fibonacci_sphere(2000)
    probe = probe[probe @ UP > math.sin(math.radians(10))]
    nearest = np.degrees(np.arccos(np.clip((probe @ dirs.T).max(axis=1), -1, 1)))
    assert nearest.max() < 9.0


def test_a_coarse_grid_is_refined_from_half_its_spacing():
    """64 candidates lie up to ~18 degrees apart: the refinement starts at 8 degrees so
    that the best candidate's neighbourhood reaches the optimum; 256 start at 4."""
    dirs = candidate_directions(UP, 64)
    probe = sh.fibonacci_sphere(2000)
    probe = probe[probe @ UP > math.sin(math.radians(10))]
    nearest = np.degrees(np.arccos(np.clip((probe @ dirs.T).max(axis=1), -1, 1)))
    steps = refine_steps(64)
    assert steps[0] == 8.0 and nearest.max() < sum(steps)  # reachable in the steps
    assert refine_steps(256) == (4.0, 2.0, 1.0)


def test_the_shading_of_many_directions_is_each_pair_s_own_ray():
    """ShadowTester.shading batches every (pixel, direction) pair that faces the direction
    into one call: each entry equals the definition, max(0, n . w) where the ray from the
    pixel (offset along its normal) towards w leaves the scene, and 0 elsewhere; only
    the facing pairs are cast, for all rows or a subset of them."""
    points, _, scene = _scene()
    rng = np.random.default_rng(3)
    normals = rng.normal(size=points.shape) + 2.0 * UP  # mostly up, some facing away
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    dirs = np.array([_sun(e, a) for e, a in [(35.0, 20.0), (10.0, 200.0), (60.0, -90.0)]])
    rows = np.sort(rng.choice(len(points), 700, replace=False))
    origins = (points + 0.02 * normals).astype(np.float32)
    for subset in (None, rows):
        tester = ShadowTester([(scene, np.eye(4))], points, normals)
        got = tester.shading(dirs, subset)
        at = np.arange(len(points)) if subset is None else subset
        cos = np.maximum(normals[at] @ dirs.T, 0.0)
        want = np.zeros_like(cos)
        for j, w in enumerate(dirs):
            facing = np.nonzero(cos[:, j] > 0.0)[0]
            rays = np.hstack([origins[at][facing], np.tile(w.astype(np.float32), (len(facing), 1))])
            blocked = scene.blocked(rays.astype(np.float32), 0.01, 100.0)
            want[facing, j] = np.where(blocked, 0.0, cos[facing, j])
        assert np.array_equal(got, want)
        assert tester.rays == int(np.sum(cos > 0.0))
        assert 0 < np.sum((cos > 0.0) & (got == 0.0)) < np.sum(cos > 0.0)  # some shadowed


def test_shadows_from_either_mesh():
    """Two meshes (the volume's and the current frame's): a ray is blocked where either
    blocks it, so a mover the volume has not fused still casts its shadow."""
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    normals = np.tile(UP, (3, 1))
    first = OcclusionScene(SurfaceMesh(*_box((0.0, 0.5, 0.0), (0.1, 0.1, 0.1)), in_world=True))
    second = OcclusionScene(SurfaceMesh(*_box((1.0, 0.5, 0.0), (0.1, 0.1, 0.1)), in_world=True))
    up = UP[None]
    alone = ShadowTester([(first, np.eye(4))], points, normals).shading(up)[:, 0]
    both = ShadowTester([(first, np.eye(4)), (second, np.eye(4))], points, normals)
    assert np.allclose(alone, [0.0, 1.0, 1.0])
    assert np.allclose(both.shading(up)[:, 0], [0.0, 0.0, 1.0])
    # a mesh in another frame: the second box seen from a camera 3 m along +x
    pose = np.eye(4)
    pose[:3, 3] = [3.0, 0.0, 0.0]
    moved = OcclusionScene(SurfaceMesh(*_box((-2.0, 0.5, 0.0), (0.1, 0.1, 0.1)), in_world=False))
    tester = ShadowTester([(first, np.eye(4)), (moved, pose)], points, normals)
    assert np.allclose(tester.shading(up)[:, 0], [0.0, 0.0, 1.0])


def test_a_source_is_as_trusted_as_its_shadow_edge_is_clear():
    conf = Confidence(samples=1000, condition_number=30.0, bands_estimated=3, value=0.05)
    clear = source_confidence(conf, 0.8)
    assert clear.value == 1.0 and clear.reason == "" and clear.samples == 1000
    faint = source_confidence(conf, 0.05)
    assert faint.value == pytest.approx(0.1)
    assert "compact source" in faint.reason and "0.05" in faint.reason
    # no step at all: the lowest confidence an estimate has, never 0 (which means none)
    flat = source_confidence(conf, -0.2)
    assert flat.value == MIN_FACTOR and "0.00" in flat.reason


def test_tracking_refines_the_last_direction_and_searches_again_when_the_light_moves():
    """A stage searching in full one frame in 5: the frames between start from the last
    best direction (far fewer directions tested, the same sun within 2 degrees); when the sun
    jumps 100 degrees the tracked direction explains little and the frame searches in full
    at once, finding the new sun."""
    from types import SimpleNamespace

    from arlight.pipeline.compact_stage import CompactLightStage

    points, normals, scene = _scene()
    bands = 3
    per_coeff = np.repeat(sh.lambert_band_factors(bands), [2 * l + 1 for l in range(bands)])
    n = len(points)
    stage = CompactLightStage(5, search_interval=5)
    found = []
    for azimuth in (20.0, 20.0, 120.0):
        sun = _sun(40.0, azimuth)
        state = SimpleNamespace(  # the light fit's FitState: the fields the stage reads
            design=sh.sh_basis(normals, bands) * per_coeff,
            albedo=np.ones(n),
            weights=np.ones(n),
            lum=_observe(points, normals, scene, sun, 2.0, _ambient()),
            rgb=None,
            penalty=penalty_matrix(bands, 4e-3, None, False),
            bands=bands,
            rows=np.arange(n),
        )
        fit, _ = stage.fit_against(
            scene,
            state,
            points[None].astype(np.float32),  # one row of "pixels", world = camera
            normals[None].astype(np.float32),
            np.zeros(n, int),
            np.arange(n),
            np.eye(4),
            UP,
            {"search_samples": 3000},
        )
        assert len(fit.sources) == 1, fit.reason
        assert angular_error_deg(fit.sources[0].direction, sun) < 3.0
        found.append((fit.tested, stage.searches))
    (searched, one), (tracked, still_one), (_, two) = found
    assert (one, still_one, two) == (1, 1, 2)
    assert tracked < 40 < searched


def test_two_lamps_are_both_found_and_one_sun_stays_one():
    """Two suns 140 degrees apart in azimuth (2.0 and 1.2): with max_sources 2 both are
    found, each within 3 degrees, the brighter first, their intensities within 20 %; under
    one sun the second search keeps nothing and says so."""
    points, normals, scene = _scene()

    def fit(lum):
        return _fit(points, normals, scene, lum, max_sources=2)

    first, second = _sun(40.0, 20.0), _sun(35.0, 160.0)
    lum = _observe(points, normals, scene, first, 2.0, _ambient()) + _observe(
        points, normals, scene, second, 1.2, np.zeros(9)
    )
    both = fit(lum)
    assert len(both.sources) == 2, both.reason
    for source, sun, power in zip(both.sources, (first, second), (2.0, 1.2), strict=True):
        assert angular_error_deg(source.direction, sun) < 3.0
        assert source.intensity == pytest.approx(power, rel=0.2)
    assert both.reason.startswith("2 compact sources")
    one = fit(_observe(points, normals, scene, first, 2.0, _ambient()))
    assert len(one.sources) == 1 and "no second" in one.reason


def test_a_tracked_frame_keeps_both_lamps():
    """With a search one frame in five, the frame after a full search that kept two lamps
    refines both and keeps both."""
    from types import SimpleNamespace

    from arlight.pipeline.compact_stage import CompactLightStage

    points, normals, scene = _scene()
    bands = 3
    per_coeff = np.repeat(sh.lambert_band_factors(bands), [2 * l + 1 for l in range(bands)])
    n = len(points)
    first, second = _sun(40.0, 20.0), _sun(35.0, 160.0)
    lum = _observe(points, normals, scene, first, 2.0, _ambient()) + _observe(
        points, normals, scene, second, 1.2, np.zeros(9)
    )
    state = SimpleNamespace(  # the light fit's FitState: the fields the stage reads
        design=sh.sh_basis(normals, bands) * per_coeff,
        albedo=np.ones(n),
        weights=np.ones(n),
        lum=lum,
        rgb=None,
        penalty=penalty_matrix(bands, 4e-3, None, False),
        bands=bands,
        rows=np.arange(n),
    )
    stage = CompactLightStage(5, search_interval=5)
    for searched in (True, False):
        fit, _ = stage.fit_against(
            scene,
            state,
            points[None].astype(np.float32),
            normals[None].astype(np.float32),
            np.zeros(n, int),
            np.arange(n),
            np.eye(4),
            UP,
            {"search_samples": 3000, "max_sources": 2},
        )
        assert stage.last_searched is searched
        assert len(fit.sources) == 2, fit.reason
        for source, sun in zip(fit.sources, (first, second), strict=True):
            assert angular_error_deg(source.direction, sun) < 3.0


def test_the_occluder_is_the_frame_s_depth_mesh_at_its_stride():
    """By default (compact_volume_mesh off) the stage tests shadows against the current
    frame's depth mesh at every `depth_stride`-th pixel, made anew each frame, in the camera
    frame; it never reads the volume (no 0.1-0.5 s mesh build)."""
    from arlight.pipeline.compact_stage import CompactLightStage

    class NoVolume:
        def __getattr__(self, name):
            raise AssertionError(f"the depth-mesh occluder read the volume ({name})")

    h, w = 30, 40
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    wall = np.stack([(u - w / 2) / 40.0 * 2.0, (v - h / 2) / 40.0 * 2.0, np.full_like(u, 2.0)], -1)
    stage = CompactLightStage(5, depth_stride=2)
    scene = stage.occluder(wall, NoVolume())
    assert not scene.in_world
    assert len(scene.mesh.triangles) == 2 * (h // 2 - 1) * (w // 2 - 1)
    # a ray from behind the wall towards the camera is blocked, one beside it is not
    rays = np.array([[0.0, 0.0, 3.0, 0.0, 0.0, -1.0], [5.0, 0.0, 3.0, 0.0, 0.0, -1.0]], np.float32)
    assert scene.blocked(rays, 0.0, 10.0).tolist() == [True, False]
    # the next frame's geometry gives the next frame's mesh
    assert stage.occluder(wall + np.float32([0.0, 0.0, 5.0]), NoVolume()) is not scene
    # the presets' stride: a mesh about 160 points wide whatever the analysed resolution;
    # the volume's mesh where asked for
    from arlight.pipeline.config import Config
    from arlight.pipeline.pipeline import Pipeline

    camera = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    strides = {
        (preset, volume): Pipeline(
            Config.from_preset(preset, compact_sources=1, compact_volume_mesh=volume), camera
        )
        .light.compact()
        .depth_stride
        for preset in ("full", "fast")
        for volume in (False, True)
    }
    assert strides == {
        ("full", False): 4,
        ("fast", False): 2,
        ("full", True): None,
        ("fast", True): None,
    }
