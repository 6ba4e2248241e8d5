"""Radiance transfer (section 5.1, eq. 6-9 of seeds/000): SSDO visibility into per-pixel SH.

The threshold chi of eq. 9 against nearest-neighbour angles, the jittered sampling, K of
eq. 8 at its ends, the Numba kernel against the NumPy oracle (main and auxiliary buffers),
the visibility-free transfer against the clamped-cosine convolution, a wall shadowing the
floor, image-space sub-sampling, and the extremes (1x1, all-missing depth).
"""

import math

import numpy as np
import pytest

from arlight.core.camera import PinholeCamera
from arlight.evaluation import angular_error_deg
from arlight.pipeline import radiance_transfer as rt
from arlight.pipeline import sh
from arlight.pipeline.config import Config
from arlight.pipeline.horizon import SupportPlane

LAMBERT_PER_COEFF = np.repeat(sh.lambert_band_factors(4), [1, 3, 5, 7])


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def _small_camera(w=12, h=9):
    return PinholeCamera(w, h, 10.0, 10.0, (w - 1) / 2.0, (h - 1) / 2.0)


def _random_scene(seed, w=12, h=9):
    """Rough random depth (0.8..1.6 m, so samples of 0.5 m hit it) with holes, random normals
    facing the camera (some unknown = 0), a random camera pose."""
    rng = np.random.default_rng(seed)
    camera = _small_camera(w, h)
    depth = rng.uniform(0.8, 1.6, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.15] = 0
    normals = rng.normal(size=(h, w, 3))
    normals[..., 2] -= 1.5
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals[rng.random((h, w)) < 0.1] = 0
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = _random_rotation(rng)
    world_from_cam[:3, 3] = rng.normal(size=3)
    return camera, camera.unproject(depth), normals.astype(np.float32), world_from_cam


def _hand_made_aux(seed, resolution=16, pixel_size_m=0.1):
    """Two orthographic buffers around the random scene: one above it looking down the
    camera's +y, one on its +x side looking along -x; random depth (1..2 m) with holes."""
    rng = np.random.default_rng(seed)
    top = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # rows: buffer x, y, z in camera
    side = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    buffer_from_cam = []
    for rot, origin_cam in ((top, [0.0, -1.5, 1.2]), (side, [1.5, 0.0, 1.2])):
        m = np.zeros((3, 4))
        m[:, :3] = rot
        m[:, 3] = -rot @ np.array(origin_cam)
        buffer_from_cam.append(m)
    depth = rng.uniform(1.0, 2.0, (2, resolution, resolution)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0
    return rt.AuxBufferArrays(depth, np.stack(buffer_from_cam), np.full(2, pixel_size_m))


class TestVisibilityThreshold:
    """chi of eq. 9."""

    def test_octahedron_exact(self):
        # Delaunay edges of +-x, +-y, +-z are all 90 degrees apart: chi = cos(45 deg)
        dirs = np.vstack([np.eye(3), -np.eye(3)])
        assert rt.visibility_threshold(dirs) == pytest.approx(math.cos(math.pi / 4), abs=1e-12)

    @pytest.mark.parametrize("n", [64, 512])
    def test_fibonacci_matches_nearest_neighbour_angles(self, n):
        # independent estimate: each point of a near-uniform set has about 6 Delaunay
        # neighbours, so the median of the 6 smallest angles per point ~ median edge angle
        dirs = sh.fibonacci_sphere(n)
        angles = np.arccos(np.clip(dirs @ dirs.T, -1.0, 1.0))
        np.fill_diagonal(angles, np.inf)
        median_nn = np.median(np.sort(angles, axis=1)[:, :6])
        chi = rt.visibility_threshold(dirs)
        assert 2.0 * math.acos(chi) == pytest.approx(median_nn, rel=0.1)
        assert chi == pytest.approx(math.cos(median_nn / 2.0), abs=2e-3)

    def test_more_directions_tighter_threshold(self):
        chis = [rt.visibility_threshold(sh.fibonacci_sphere(n)) for n in (16, 64, 256)]
        assert 0.0 < chis[0] < chis[1] < chis[2] < 1.0


class TestSampling:
    def test_jittered_directions_unit_and_deterministic(self):
        a = rt.jittered_directions(64, np.random.default_rng(7))
        b = rt.jittered_directions(64, np.random.default_rng(7))
        c = rt.jittered_directions(64, np.random.default_rng(8))
        assert a.shape == (64, 3)
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
        np.testing.assert_array_equal(a, b)
        assert not np.allclose(a, c)
        # jittered within its cell: each stays near its Fibonacci point
        base = sh.fibonacci_sphere(64)
        cell = math.sqrt(4.0 * math.pi / 64)
        assert np.arccos(np.clip((a * base).sum(axis=1), -1, 1)).max() < 1.5 * cell

    def test_pattern_deterministic_per_seed(self):
        cfg = Config().replace(rt_directions=32, rt_steps=3, rt_radius_m=0.4, seed=3)
        tp = cfg.transfer
        p, q = rt.make_sampling_pattern(tp, cfg.seed), rt.make_sampling_pattern(tp, cfg.seed)
        np.testing.assert_array_equal(p.directions, q.directions)
        np.testing.assert_array_equal(p.radii, q.radii)
        assert p.chi == q.chi == rt.visibility_threshold(p.directions)
        other = rt.make_sampling_pattern(tp, 4)
        assert not np.allclose(p.directions, other.directions)

    def test_radii_stratified_within_radius(self):
        cfg = Config().replace(rt_directions=32, rt_steps=3, rt_radius_m=0.4)
        tp = cfg.transfer
        radii = rt.make_sampling_pattern(tp, cfg.seed).radii
        assert radii.shape == (2, 2, 32, 3)
        assert radii.min() > 0.0 and radii.max() <= 0.4
        for s in range(3):  # step s draws from (s, s + 1] / steps * radius
            assert np.all(radii[..., s] >= s / 3 * 0.4)
            assert np.all(radii[..., s] <= (s + 1) / 3 * 0.4)


class TestOcclusionK:
    """K of eq. 7-8, in the kernel's helper and the oracle's."""

    CHI = 0.97

    def _both(self, x, s, w):
        k_kernel = rt._occlusion(*x, *(x + w), *s, *w, self.CHI)
        k_ref = rt._occlusion_reference(np.array(x), np.array(s), np.array(w), self.CHI)
        assert k_kernel == pytest.approx(k_ref, abs=1e-12)
        return k_kernel

    def test_occluder_along_w_blocks_fully(self):
        w = np.array([0.0, 0.6, 0.8])
        assert self._both(np.zeros(3), 0.3 * w, w) == pytest.approx(0.0, abs=1e-12)

    def test_perpendicular_occluder_does_not_block(self):
        w = np.array([0.0, 0.0, 1.0])
        assert self._both(np.zeros(3), np.array([0.2, 0.0, 0.0]), w) == pytest.approx(1.0)

    def test_rises_with_angle(self):
        w = np.array([0.0, 0.0, 1.0])
        k = [
            self._both(np.zeros(3), np.array([math.sin(a), 0.0, math.cos(a)]), w)
            for a in np.radians([0, 20, 40, 60, 89])
        ]
        assert np.all(np.diff(k) > 0)
        assert k[3] == pytest.approx((1 - math.cos(math.radians(60))) / self.CHI)

    def test_coincident_points_not_occluded(self):
        x = np.array([0.1, 0.2, 1.0])
        assert self._both(x, x.copy(), np.array([0.0, 0.0, 1.0])) == 1.0


class TestKernelAgainstReference:
    @pytest.mark.parametrize("seed, step, steps", [(0, 1, 1), (1, 1, 2), (2, 2, 2)])
    @pytest.mark.parametrize("with_aux", [False, True])
    def test_random_scene_with_holes(self, seed, step, steps, with_aux):
        camera, points, normals, world_from_cam = _random_scene(seed)
        aux = _hand_made_aux(seed) if with_aux else None
        cfg = Config().replace(rt_directions=32, rt_steps=steps, rt_subsample=step, seed=seed)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        fast = rt.compute_transfer(points, normals, camera, world_from_cam, pattern, aux, tp)
        ref = rt.transfer_reference(points, normals, camera, world_from_cam, pattern, aux, tp)
        np.testing.assert_array_equal(fast.valid, ref.valid)
        np.testing.assert_array_equal(fast.pixel_u, ref.pixel_u)
        np.testing.assert_array_equal(fast.pixel_v, ref.pixel_v)
        assert fast.transfer.dtype == np.float32 and fast.transfer.shape[-1] == 16
        np.testing.assert_allclose(fast.transfer, ref.transfer, atol=1e-4)
        # holes are invalid with zero transfer, and the scene really occludes something
        assert 0 < fast.valid.sum() < fast.valid.size
        assert np.all(fast.transfer[~fast.valid] == 0)
        free = rt.compute_transfer(
            points,
            normals,
            camera,
            world_from_cam,
            pattern,
            aux,
            cfg.replace(visibility=False).transfer,
        )
        assert (free.transfer[..., 0] - fast.transfer[..., 0])[fast.valid].mean() > 0.05

    def test_aux_buffers_add_occlusion(self):
        camera, points, normals, world_from_cam = _random_scene(0)
        cfg = Config().replace(rt_directions=32)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        main_only = rt.compute_transfer(points, normals, camera, world_from_cam, pattern, None, tp)
        with_aux = rt.compute_transfer(
            points, normals, camera, world_from_cam, pattern, _hand_made_aux(0), tp
        )
        dc_drop = (main_only.transfer[..., 0] - with_aux.transfer[..., 0])[main_only.valid]
        assert np.all(dc_drop >= -1e-6) and dc_drop.mean() > 0.05


class TestTwoScenesAtOnce:
    """transfer_pair_at_pixels (the renderer's real pixels without and with the virtual
    objects) gives exactly what two transfer_at_pixels calls give."""

    @pytest.mark.parametrize(
        "seed, steps, with_plane", [(0, 1, False), (1, 2, True), (2, 2, False)]
    )
    def test_pair_equals_two_calls(self, seed, steps, with_plane):
        camera, points, normals, world_from_cam = _random_scene(seed, w=24, h=18)
        rng = np.random.default_rng(seed + 10)
        # the second scene: a "virtual" block in front of the left third of the image,
        # and in the auxiliary buffers' middle texels
        depth_second = points[..., 2].copy()
        block = np.zeros(depth_second.shape, bool)
        block[4:14, 2:8] = True
        depth_second[block] = 0.7
        points_second = camera.unproject(depth_second)
        aux = _hand_made_aux(seed)
        aux_second = rt.AuxBufferArrays(aux.depth.copy(), aux.buffer_from_cam, aux.pixel_size)
        aux_second.depth[:, 6:10, 6:10] = 0.9
        radiance = rng.uniform(0.1, 1.0, (*depth_second.shape, 3)).astype(np.float32)
        radiance_second = radiance.copy()
        radiance_second[block] = (0.9, 0.1, 0.1)
        plane = None
        if with_plane:
            up = np.array([0.0, -1.0, 0.0])
            plane = SupportPlane(up, 1.2, np.zeros(depth_second.shape, bool))
        tp = Config().replace(rt_directions=32, rt_steps=steps, seed=seed).transfer
        pattern = rt.make_sampling_pattern(tp, seed)
        vs, us = np.nonzero(~block & (points[..., 2] > 0))
        first = rt.transfer_at_pixels(
            points, normals, camera, world_from_cam, pattern, aux, tp, us, vs, radiance, plane
        )
        second = rt.transfer_at_pixels(
            points_second,
            normals,
            camera,
            world_from_cam,
            pattern,
            aux_second,
            tp,
            us,
            vs,
            radiance_second,
            plane,
        )
        (t1, b1), (t2, b2), valid = rt.transfer_pair_at_pixels(
            points,
            points_second,
            normals,
            camera,
            world_from_cam,
            pattern,
            aux,
            aux_second,
            tp,
            us,
            vs,
            radiance,
            radiance_second,
            plane,
        )
        np.testing.assert_array_equal(valid, first[2])
        np.testing.assert_array_equal(valid, second[2])
        for got, want in ((t1, first[0]), (b1, first[1]), (t2, second[0]), (b2, second[1])):
            np.testing.assert_array_equal(got, want)
        # the scenes really differ: the block and its aux texels shadow some pixels
        assert np.abs(t1 - t2).max() > 0.05 and np.abs(b1 - b2).max() > 0.01


def _plane_facing_camera(seed):
    """A 12x9 plane at 1 m facing the camera, seen from a random camera pose: camera,
    points, normals (camera frame), world_from_cam."""
    camera = _small_camera()
    points = camera.unproject(np.full((9, 12), 1.0, np.float32))
    normals = np.zeros_like(points)
    normals[..., 2] = -1.0
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = _random_rotation(np.random.default_rng(seed))
    return camera, points, normals, world_from_cam


class TestVisibilityFree:
    """visibility=False: T(n) is the clamped-cosine transfer A_l Y_lm(n) (by quadrature)."""

    def test_plane_facing_camera_is_lambert_convolution(self):
        camera, points, normals, world_from_cam = _plane_facing_camera(3)
        cfg = Config().replace(rt_directions=512, visibility=False)
        tp = cfg.transfer
        res = rt.compute_transfer(
            points,
            normals,
            camera,
            world_from_cam,
            rt.make_sampling_pattern(tp, cfg.seed),
            None,
            tp,
        )
        assert res.valid.all()
        t = res.transfer.reshape(-1, 16)
        np.testing.assert_allclose(t, t[:1].repeat(len(t), axis=0), atol=1e-6)
        n_world = world_from_cam[:3, :3] @ np.array([0.0, 0.0, -1.0])
        expected = LAMBERT_PER_COEFF * sh.sh_basis(n_world, 4)
        np.testing.assert_allclose(t[0], expected, atol=0.03)
        # T . l reproduces the irradiance of l at the normal
        rng = np.random.default_rng(4)
        for _ in range(5):
            light = rng.normal(size=16)
            irradiance = sh.evaluate(sh.irradiance_from_radiance(light), n_world[None])[0]
            assert float(t[0] @ light) == pytest.approx(
                irradiance, abs=0.02 * np.linalg.norm(light)
            )


class TestExactUnoccluded:
    """rt_exact_unoccluded: the control variate makes the unoccluded part of the transfer
    exact at any direction count, and leaves the occluded part's deficit in place."""

    def _plane(self, visibility):
        camera, points, normals, world_from_cam = _plane_facing_camera(5)
        cfg = Config().replace(rt_directions=64, visibility=visibility)
        pattern = rt.make_sampling_pattern(cfg.transfer, cfg.seed)
        res = rt.compute_transfer(
            points, normals, camera, world_from_cam, pattern, None, cfg.transfer
        )
        samples = rt.transfer_samples(res, None, 1000, 0)
        n_world = world_from_cam[:3, :3] @ np.array([0.0, 0.0, -1.0])
        table = rt.quadrature_error_table(pattern, 4)
        return samples, normals, world_from_cam, table, n_world

    def test_unoccluded_plane_is_exact_at_64_directions(self):
        samples, normals, pose, table, n_world = self._plane(visibility=False)
        expected = LAMBERT_PER_COEFF * sh.sh_basis(n_world, 4)
        raw_error = np.abs(samples.transfer - expected).max()
        assert raw_error > 0.01  # 64 directions alone miss (what the correction is for)
        fixed = rt.with_exact_unoccluded(samples, normals, pose, table)
        # exact but for the table's bilinear lookup (128 texels a side: ~1.4 degrees)
        np.testing.assert_allclose(
            fixed.transfer, np.broadcast_to(expected, fixed.transfer.shape), atol=1.5e-3
        )
        assert fixed.transfer.dtype == samples.transfer.dtype

    def test_blocked_light_stays_blocked(self):
        camera, points, normals, pose, _, on_wall = _floor_and_wall()
        cfg = Config().replace(rt_directions=64)
        pattern = rt.make_sampling_pattern(cfg.transfer, cfg.seed)
        res = rt.compute_transfer(points, normals, camera, pose, pattern, None, cfg.transfer)
        samples = rt.transfer_samples(res, None, 10**6, 0)
        fixed = rt.with_exact_unoccluded(
            samples, normals, pose, rt.quadrature_error_table(pattern, 4)
        )
        # band 0 is the visible fraction of the clamped cosine: the correction moves it by
        # the quadrature error only, never restores what the wall blocks for the floor
        floor_near_wall = ~on_wall[samples.pixel_v, samples.pixel_u]
        exact_open = LAMBERT_PER_COEFF[0] * sh.sh_basis(np.array([0.0, 0.0, 1.0]), 4)[0]
        blocked = samples.transfer[floor_near_wall, 0] < 0.8 * exact_open
        assert blocked.any()
        assert (fixed.transfer[floor_near_wall, 0][blocked] < 0.9 * exact_open).all()

    def test_table_matches_the_direct_correction(self):
        cfg = Config()
        pattern = rt.make_sampling_pattern(cfg.transfer, cfg.seed)
        table = rt.quadrature_error_table(pattern, 4)
        rng = np.random.default_rng(7)
        n = rng.normal(size=(5000, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n[:, 2] = -np.abs(n[:, 2])  # seen surfaces face the camera
        h, w = 50, 100
        normals = n.reshape(h, w, 3).astype(np.float32)
        v, u = np.divmod(np.arange(h * w), w)
        samples = rt.TransferSamples(v, u, np.zeros((h * w, 16), np.float32), None)
        pose = np.eye(4)
        pose[:3, :3] = _random_rotation(rng)
        fixed = rt.with_exact_unoccluded(samples, normals, pose, table)
        direct = rt.unoccluded_quadrature_error(
            n @ pose[:3, :3].T, pattern.directions @ pose[:3, :3].T, 4
        )
        scale = np.abs(direct).max()
        assert np.abs(fixed.transfer - direct).max() < 0.03 * scale
        assert np.median(np.abs(fixed.transfer - direct)) < 0.003 * scale

    def test_pixels_without_normals_are_untouched(self):
        samples, normals, pose, table, _ = self._plane(visibility=False)
        normals = normals.copy()
        normals[samples.pixel_v[0], samples.pixel_u[0]] = 0.0
        fixed = rt.with_exact_unoccluded(samples, normals, pose, table)
        np.testing.assert_array_equal(fixed.transfer[0], samples.transfer[0])


def _floor_and_wall(w=64, h=48, wall_y=0.5, wall_height=0.5):
    """Analytic depth of a floor z_w = 0 with a wall y_w = wall_y (0 <= z_w <= wall_height)
    facing a camera at (0, -1.6, 1.2) that looks down at (0, 0.2, 0).

    Returns camera, points (H, W, 3), normals (camera frame), world_from_cam, world points,
    wall mask.
    """
    camera = PinholeCamera(w, h, 50.0, 50.0, (w - 1) / 2.0, (h - 1) / 2.0)
    eye = np.array([0.0, -1.6, 1.2])
    forward = np.array([0.0, 0.2, 0.0]) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = np.stack([right, down, forward], axis=1)
    world_from_cam[:3, 3] = eye
    rays = camera.unproject(np.ones((h, w), np.float32)).astype(np.float64)  # z = 1
    d = rays @ world_from_cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d[..., 2] < 0, -eye[2] / d[..., 2], np.inf)
        t_wall = np.where(d[..., 1] > 0, (wall_y - eye[1]) / d[..., 1], np.inf)
    z_wall = eye[2] + t_wall * d[..., 2]
    on_wall = (z_wall >= 0) & (z_wall <= wall_height) & (t_wall < t_floor)
    t = np.where(on_wall, t_wall, t_floor)
    depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
    n_world = np.where(on_wall[..., None], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0])
    normals = (n_world @ world_from_cam[:3, :3]).astype(np.float32)  # R^T n per pixel
    normals[depth == 0] = 0
    world = eye + depth[..., None] * d
    return camera, camera.unproject(depth), normals, world_from_cam, world, on_wall


class TestOccluder:
    def test_wall_shadows_the_floor_next_to_it(self):
        camera, points, normals, world_from_cam, world, on_wall = _floor_and_wall()
        cfg = Config().replace(rt_directions=64, rt_steps=2)
        tp = cfg.transfer
        res = rt.compute_transfer(
            points,
            normals,
            camera,
            world_from_cam,
            rt.make_sampling_pattern(tp, cfg.seed),
            None,
            tp,
        )
        floor = ~on_wall & res.valid
        central = np.abs(world[..., 0]) < 0.4
        near = floor & central & (world[..., 1] > 0.3) & (world[..., 1] < 0.45)
        far = floor & central & (world[..., 1] > -0.8) & (world[..., 1] < -0.5)
        assert near.sum() >= 10 and far.sum() >= 10
        t_near, t_far = res.transfer[near].mean(axis=0), res.transfer[far].mean(axis=0)
        # far from the wall the floor sees the whole upper hemisphere: A_0 Y_00
        assert t_far[0] == pytest.approx(
            LAMBERT_PER_COEFF[0] * sh.sh_basis(np.array([0.0, 0.0, 1.0]), 1)[0], rel=0.05
        )
        assert t_near[0] < 0.9 * t_far[0]
        # the wall (+y_w) blocks directions towards it: band 1 tilts to -y_w, away from it
        d_near, d_far = sh.dominant_direction(t_near), sh.dominant_direction(t_far)
        assert d_near[1] < -0.15
        assert abs(d_far[1]) < 0.05 and d_far[2] > 0.99
        assert angular_error_deg(d_far, [0.0, 0.0, 1.0]) < 5.0


class TestSubsampling:
    def test_grid_shape_and_pixels(self):
        camera, points, normals, world_from_cam = _random_scene(5, w=13, h=10)
        cfg = Config().replace(rt_directions=16, rt_subsample=4)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        sub = rt.compute_transfer(points, normals, camera, world_from_cam, pattern, None, tp)
        assert sub.transfer.shape == (math.ceil(10 / 4), math.ceil(13 / 4), 16)
        assert sub.valid.shape == (3, 4)
        np.testing.assert_array_equal(sub.pixel_u, [2, 6, 10, 12])  # last clamped to W - 1
        np.testing.assert_array_equal(sub.pixel_v, [2, 6, 9])
        # each grid cell is the full-resolution transfer of its pixel (same 2x2 radii)
        full = rt.compute_transfer(
            points,
            normals,
            camera,
            world_from_cam,
            pattern,
            None,
            cfg.replace(rt_subsample=1).transfer,
        )
        grid = np.ix_(sub.pixel_v, sub.pixel_u)
        np.testing.assert_array_equal(sub.valid, full.valid[grid])
        np.testing.assert_allclose(sub.transfer, full.transfer[grid], atol=1e-6)


class TestExtremes:
    @pytest.mark.parametrize("step", [1, 4])
    def test_one_pixel_image(self, step):
        camera = PinholeCamera(1, 1, 1.0, 1.0, 0.0, 0.0)
        cfg = Config().replace(rt_directions=16, rt_subsample=step)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        normal = np.array([[[0.0, 0.0, -1.0]]], np.float32)
        missing = rt.compute_transfer(
            camera.unproject(np.zeros((1, 1), np.float32)),
            normal,
            camera,
            np.eye(4),
            pattern,
            None,
            tp,
        )
        assert missing.transfer.shape == (1, 1, 16) and not missing.valid.any()
        assert np.all(missing.transfer == 0)
        present = rt.compute_transfer(
            camera.unproject(np.ones((1, 1), np.float32)),
            normal,
            camera,
            np.eye(4),
            pattern,
            None,
            tp,
        )
        assert present.valid.all() and np.all(np.isfinite(present.transfer))
        assert present.transfer[0, 0, 0] > 0

    @pytest.mark.parametrize("fill", [0.0, np.nan])
    def test_all_missing_depth(self, fill):
        camera = _small_camera()
        depth = np.full((9, 12), fill, np.float32)
        points = camera.unproject(depth)
        normals = np.zeros((9, 12, 3), np.float32)
        normals[..., 2] = -1.0  # even with normals, no depth means no transfer
        cfg = Config().replace(rt_directions=16)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        aux = _hand_made_aux(0)
        for fn in (rt.compute_transfer, rt.transfer_reference):
            res = fn(points, normals, camera, np.eye(4), pattern, aux, tp)
            assert not res.valid.any()
            assert np.all(res.transfer == 0)


class TestUpsampling:
    def _grid(self, valid: np.ndarray) -> rt.TransferResult:
        """A 3 x 4 grid over a 10 x 13 image whose transfer is linear in the pixel position."""
        u, v = np.array([2, 6, 10, 12]), np.array([2, 6, 9])
        uu, vv = np.meshgrid(u, v)
        transfer = np.stack([uu, vv, uu + 2 * vv], axis=-1).astype(np.float32)
        return rt.TransferResult(transfer, valid, u, v)

    def test_linear_field_is_reproduced_between_grid_points(self):
        up = rt.upsample_transfer(self._grid(np.ones((3, 4), bool)), np.ones((10, 13), bool))
        assert up.transfer.shape == (10, 13, 3) and up.valid.all()
        uu, vv = np.meshgrid(np.arange(13), np.arange(10))
        inside = (uu >= 2) & (vv >= 2)  # beyond the first grid point the field is clamped
        np.testing.assert_allclose(up.transfer[..., 0][inside], uu[inside], atol=1e-4)
        np.testing.assert_allclose(up.transfer[..., 1][inside], vv[inside], atol=1e-4)

    def test_invalid_grid_point_and_missing_geometry_are_not_interpolated(self):
        valid = np.ones((3, 4), bool)
        valid[1, 1] = False  # grid pixel (u=6, v=6)
        geometry = np.ones((10, 13), bool)
        geometry[0, 0] = False
        up = rt.upsample_transfer(self._grid(valid), geometry)
        assert not up.valid[6, 6] and not up.valid[4, 4] and not up.valid[0, 0]
        assert up.valid[6, 11] and up.valid[9, 0]
        assert np.all(up.transfer[~up.valid] == 0)

    def test_full_resolution_grid_is_returned_unchanged(self):
        full = rt.TransferResult(
            np.ones((4, 5, 2), np.float32), np.ones((4, 5), bool), np.arange(5), np.arange(4)
        )
        assert rt.upsample_transfer(full, np.ones((4, 5), bool)) is full


class TestTransferSamples:
    """`transfer_samples`: what the light estimate uses, the up-sampling done at the chosen
    pixels only."""

    _grid = TestUpsampling._grid

    def test_every_pixel_matches_the_full_upsampling(self):
        valid = np.ones((3, 4), bool)
        valid[1, 1] = False
        geometry = np.ones((10, 13), bool)
        geometry[0, 0] = False
        grid = self._grid(valid)
        up = rt.upsample_transfer(grid, geometry)
        got = rt.transfer_samples(grid, geometry, max_pixels=10**6, seed=0)
        kept = np.zeros((10, 13), bool)
        kept[got.pixel_v, got.pixel_u] = True
        np.testing.assert_array_equal(kept, up.valid)  # the same pixels kept
        # cv2.remap places its taps to 1/32 pixel: its field is within that of the exact one
        np.testing.assert_allclose(got.transfer, up.transfer[got.pixel_v, got.pixel_u], atol=0.2)
        inside = (got.pixel_u >= 2) & (got.pixel_v >= 2)
        np.testing.assert_allclose(got.transfer[inside, 0], got.pixel_u[inside], atol=1e-4)
        np.testing.assert_allclose(got.transfer[inside, 1], got.pixel_v[inside], atol=1e-4)

    def test_at_most_max_pixels_seeded(self):
        grid = self._grid(np.ones((3, 4), bool))
        geometry = np.ones((10, 13), bool)
        a = rt.transfer_samples(grid, geometry, max_pixels=20, seed=1)
        b = rt.transfer_samples(grid, geometry, max_pixels=20, seed=1)
        assert len(a.pixel_v) == 20
        np.testing.assert_array_equal(a.pixel_u, b.pixel_u)
        np.testing.assert_array_equal(a.transfer, b.transfer)

    def test_without_interpolation_the_valid_grid_points(self):
        valid = np.ones((3, 4), bool)
        valid[2, 3] = False
        got = rt.transfer_samples(self._grid(valid), None, max_pixels=100, seed=0)
        assert len(got.pixel_v) == 11
        assert (12, 9) not in set(zip(got.pixel_u.tolist(), got.pixel_v.tolist(), strict=True))
        np.testing.assert_array_equal(got.transfer[:, 0], got.pixel_u)


class TestBounce:
    def test_blocked_light_is_returned_by_the_occluders(self):
        """With a uniform luminance c, what a direction loses in K it gains as bounce:
        T_00 / Y_00 + B / c equals the visibility-free cosine sum, pixel by pixel."""
        camera, points, normals, world_from_cam, world, on_wall = _floor_and_wall()
        cfg = Config().replace(rt_directions=64, rt_steps=2)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        c = 0.37
        lum = np.full(points.shape[:2], c, np.float32)
        res = rt.compute_transfer(
            points, normals, camera, world_from_cam, pattern, None, tp, luminance=lum
        )
        free = rt.compute_transfer(
            points,
            normals,
            camera,
            world_from_cam,
            pattern,
            None,
            cfg.replace(visibility=False).transfer,
        )
        y00 = sh.sh_basis(np.array([0.0, 0.0, 1.0]), 1)[0]
        v = res.valid
        assert res.bounce is not None and np.count_nonzero(res.bounce[v] > 1e-3) >= 10
        np.testing.assert_allclose(
            res.transfer[v, 0] / y00 + res.bounce[v] / c,
            free.transfer[v, 0] / y00,
            rtol=1e-4,
            atol=1e-5,
        )
        # without a luminance image there is no bounce term
        plain = rt.compute_transfer(points, normals, camera, world_from_cam, pattern, None, tp)
        assert plain.bounce is None
        np.testing.assert_array_equal(plain.transfer, res.transfer)

    def test_luminance_of_the_wrong_size_is_refused(self):
        camera, points, normals, world_from_cam, _, _ = _floor_and_wall()
        cfg = Config().replace(rt_directions=16)
        tp = cfg.transfer
        with pytest.raises(ValueError, match="luminance"):
            rt.compute_transfer(
                points,
                normals,
                camera,
                world_from_cam,
                rt.make_sampling_pattern(tp, cfg.seed),
                None,
                tp,
                luminance=np.ones((3, 3), np.float32),
            )


def _floor_plane(world_from_cam, on_floor):
    """The floor z_w = 0 of `_floor_and_wall` as a SupportPlane in the camera frame."""
    up_cam = world_from_cam[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    return SupportPlane(up_cam, float(world_from_cam[2, 3]), on_floor)


class TestHorizonPlane:
    """plane=...: directions below the support plane's horizon see the ground, not the light."""

    @pytest.mark.parametrize("seed", [0, 1])
    def test_kernel_matches_reference(self, seed):
        camera, points, normals, world_from_cam = _random_scene(seed)
        rng = np.random.default_rng(seed)
        up = rng.normal(size=3)
        up /= np.linalg.norm(up)
        plane = SupportPlane(up, -float(np.median(points[..., 2])) * up[2], np.zeros((1, 1), bool))
        cfg = Config().replace(rt_directions=32, seed=seed)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        fast = rt.compute_transfer(
            points, normals, camera, world_from_cam, pattern, None, tp, plane=plane
        )
        ref = rt.transfer_reference(
            points, normals, camera, world_from_cam, pattern, None, tp, plane=plane
        )
        np.testing.assert_allclose(fast.transfer, ref.transfer, atol=1e-4)
        without = rt.compute_transfer(points, normals, camera, world_from_cam, pattern, None, tp)
        assert np.abs(without.transfer - fast.transfer).max() > 0.05  # the plane did something

    def test_wall_sees_no_light_from_below_and_the_ground_instead(self):
        camera, points, normals, world_from_cam, world, on_wall = _floor_and_wall()
        cfg = Config().replace(rt_directions=128, rt_steps=2)
        tp = cfg.transfer
        pattern = rt.make_sampling_pattern(tp, cfg.seed)
        plane = _floor_plane(world_from_cam, ~on_wall & (points[..., 2] > 0))
        c = 0.37
        lum = np.full(points.shape[:2], c, np.float32)
        res = rt.compute_transfer(
            points, normals, camera, world_from_cam, pattern, None, tp, luminance=lum, plane=plane
        )
        free = rt.compute_transfer(
            points,
            normals,
            camera,
            world_from_cam,
            pattern,
            None,
            cfg.replace(visibility=False).transfer,
        )
        v = res.valid
        # a light only below the floor's horizon reaches no pixel
        below = sh.directional_light(
            np.array([0.3, -0.2, -0.93]) / np.linalg.norm([0.3, -0.2, -0.93]), 1.0, 4
        )
        below_only = np.clip(sh.sh_basis(sh.fibonacci_sphere(4096), 4) @ below, 0, None)
        below_only[sh.fibonacci_sphere(4096)[:, 2] >= 0] = 0  # cut at the horizon exactly
        light = sh.project_samples(
            sh.fibonacci_sphere(4096), below_only, np.full(4096, 4 * np.pi / 4096), 4
        )
        lit = res.transfer[v] @ light
        assert np.abs(lit).max() < 0.15 * np.abs(free.transfer[v] @ light).max()
        # what the wall loses below the horizon comes back as the ground's luminance
        y00 = sh.sh_basis(np.array([0.0, 0.0, 1.0]), 1)[0]
        wall = v & on_wall[res.pixel_v][:, res.pixel_u]
        assert wall.sum() > 20
        np.testing.assert_allclose(
            res.transfer[wall, 0] / y00 + res.bounce[wall] / c,
            free.transfer[wall, 0] / y00,
            rtol=1e-4,
            atol=1e-5,
        )
        # the wall's lower half of directions is gone from the transfer: about half its DC
        ratio = res.transfer[wall, 0] / free.transfer[wall, 0]
        assert 0.3 < np.median(ratio) < 0.7


class TestEdgeRefinement:
    """`interpolated_samples` with edge_spread: pixels between grid points whose transfers
    differ (a shadow edge) are handed back for their own transfer, the rest interpolated."""

    def _shadow_edge_grid(self) -> rt.TransferResult:
        """The 3 x 4 grid of TestUpsampling, band 0 halved (shadowed) right of column 6."""
        u, v = np.array([2, 6, 10, 12]), np.array([2, 6, 9])
        transfer = np.ones((3, 4, 4), np.float32)
        transfer[:, 2:, :] *= 0.5
        return rt.TransferResult(transfer, np.ones((3, 4), bool), u, v)

    def test_pixels_across_the_edge_are_refined_and_no_others(self):
        grid = self._shadow_edge_grid()
        geometry = np.ones((10, 13), bool)
        samples, (vs, us) = rt.interpolated_samples(grid, geometry, 10**6, 0, edge_spread=0.1)
        # between grid columns 6 and 10 the corners differ: those pixels are the edge
        assert len(us) and np.all((us > 6) & (us < 10))
        assert not np.any((samples.pixel_u > 6) & (samples.pixel_u < 10))
        assert len(samples.pixel_v) + len(vs) == 10 * 13  # every pixel, one way or the other
        np.testing.assert_allclose(samples.transfer[samples.pixel_u <= 6, 0], 1.0, atol=1e-6)

    def test_off_by_default_and_identical_to_transfer_samples(self):
        grid = self._shadow_edge_grid()
        geometry = np.ones((10, 13), bool)
        samples, (vs, us) = rt.interpolated_samples(grid, geometry, 10**6, 0)
        plain = rt.transfer_samples(grid, geometry, 10**6, 0)
        assert len(vs) == len(us) == 0
        np.testing.assert_array_equal(samples.transfer, plain.transfer)
