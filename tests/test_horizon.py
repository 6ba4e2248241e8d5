"""The supporting plane's "up" (pipeline/horizon.py) and the below-horizon prior of the light
estimate (light_estimation.below_horizon_gram, estimate_light(up=...))."""

import math

import numpy as np
import pytest

from arlight.core.camera import PinholeCamera
from arlight.evaluation import angular_error_deg
from arlight.pipeline import light_estimation as le
from arlight.pipeline import sh
from arlight.pipeline.config import EstimationParams
from arlight.pipeline.horizon import support_plane, support_plane_up

LAMBERT_PER_COEFF = np.repeat(sh.lambert_band_factors(4), [1, 3, 5, 7])


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class TestSupportPlaneUp:
    def _image(self, floor_normal, floor_rows=60, seed=0):
        """100 x 80 normals: `floor_rows` rows of a noisy floor, the rest walls facing the
        camera (-z) and the sides; a few unknown (zero) normals."""
        rng = np.random.default_rng(seed)
        n = np.zeros((100, 80, 3))
        n[:floor_rows] = _unit(floor_normal + rng.normal(scale=0.03, size=(floor_rows, 80, 3)))
        walls = rng.choice(3, size=(100 - floor_rows, 80))
        n[floor_rows:] = np.array([[0, 0, -1.0], [0.8, 0, -0.6], [-0.8, 0, -0.6]])[walls]
        n[rng.random((100, 80)) < 0.05] = 0
        return n.astype(np.float32)

    def test_floor_normal_found_among_walls(self):
        floor = _unit([0.1, -0.9, -0.4])  # facing up in the image (camera y points down)
        up = support_plane_up(self._image(floor), stride=1)
        assert up is not None and angular_error_deg(up, floor) < 2.0

    def test_no_upward_surface_no_answer(self):
        assert support_plane_up(self._image(_unit([0, 0, -1.0])), stride=1) is None
        assert support_plane_up(np.zeros((10, 10, 3), np.float32)) is None

    def test_small_upward_patch_is_not_a_support_plane(self):
        assert support_plane_up(self._image(_unit([0, -1.0, 0]), floor_rows=5), stride=1) is None


class TestSupportPlane:
    def _floor_and_table(self, seed=0):
        """A camera 1.2 m above a floor, pitched 35 degrees down; a table top 0.4 m high
        covers a quarter of the image. Points and normals in the camera frame, with noise."""
        rng = np.random.default_rng(seed)
        camera = PinholeCamera(160, 120, 120.0, 120.0, 79.5, 59.5)
        pitch = math.radians(35.0)
        # columns: the camera's x (right), y (down), z (forward) in the world (y up); symmetric
        r_wc = np.array(
            [
                [1.0, 0, 0],
                [0, -math.cos(pitch), -math.sin(pitch)],
                [0, -math.sin(pitch), math.cos(pitch)],
            ]
        )
        rays = camera.unproject(np.ones((120, 160), np.float32)).astype(np.float64)
        d_world = rays @ r_wc.T
        height = np.full((120, 160), 0.0)
        height[60:, 40:120] = 0.4  # the table, nearer the camera (lower in the image)
        t = (height - 1.2) / d_world[..., 1]
        depth = (t * rays[..., 2]).astype(np.float32)
        depth += rng.normal(scale=0.002, size=depth.shape).astype(np.float32)
        points = camera.unproject(depth)
        up_cam = r_wc.T @ np.array([0.0, 1.0, 0.0])
        normals = np.broadcast_to(up_cam, points.shape).astype(np.float32).copy()
        return points, normals, up_cam, height

    def test_floor_found_with_its_height_and_pixels(self):
        points, normals, up_cam, height = self._floor_and_table()
        plane = support_plane(normals, points, stride=1)
        assert plane is not None and angular_error_deg(plane.up, up_cam) < 1.0
        assert plane.offset == pytest.approx(1.2, abs=0.01)  # the camera's height above it
        np.testing.assert_allclose(plane.height(points[height == 0]), 0.0, atol=0.02)
        np.testing.assert_allclose(plane.height(points[height > 0]), 0.4, atol=0.02)
        assert plane.on_plane[height == 0].mean() > 0.95
        assert not plane.on_plane[height > 0].any()

    def test_no_upward_surface_no_plane(self):
        points, normals, _, _ = self._floor_and_table()
        normals[:] = [0.0, 0.0, -1.0]
        assert support_plane(normals, points) is None


class TestBelowHorizonPrior:
    def test_ground_glow_costs_nothing_and_a_lobe_below_costs_much(self):
        up = np.array([0.0, 1.0, 0.0])
        q = le.below_horizon_gram(up, 4, ground_albedo=0.3)
        assert np.all(np.linalg.eigvalsh(q) > -1e-9)  # positive semi-definite
        above = sh.directional_light(_unit([0.3, 0.8, 0.2]), 1.0, 4)
        below = sh.directional_light(_unit([0.3, -0.8, 0.2]), 1.0, 4)
        assert below @ q @ below > 5.0 * (above @ q @ above)
        # a constant radiance c over the sphere: its lower half should be 0.3 / pi * E_up
        # (E_up = pi c) = 0.3 c, so the prior charges (0.7 c)^2 over 2 pi steradians
        c = 1.0
        const = np.zeros(16)
        const[0] = c * math.sqrt(4.0 * math.pi)
        assert const @ q @ const == pytest.approx(0.49 * 2.0 * math.pi, rel=0.05)

    def _data(self, direction, m=4000, seed=0):
        rng = np.random.default_rng(seed)
        n = _unit(rng.normal(size=(m, 3)))
        t = sh.sh_basis(n, 4) * LAMBERT_PER_COEFF
        light = sh.directional_light(_unit(direction), 0.6, 4)
        light[0] += 0.3
        lum = t @ light
        return t, np.repeat(lum[:, None], 3, axis=1), light

    def test_light_above_the_horizon_is_left_alone(self):
        t, color, light = self._data([0.3, 0.8, 0.5])
        free = le.estimate_light(t, color, EstimationParams())
        with_up = le.estimate_light(t, color, EstimationParams(), up=np.array([0.0, 1.0, 0.0]))
        assert not with_up.horizon_prior_used
        np.testing.assert_allclose(with_up.sh, free.sh)

    def test_light_below_the_horizon_is_refit_with_the_prior(self):
        t, color, light = self._data([0.3, -0.6, 0.5])
        free = le.estimate_light(t, color, EstimationParams())
        with_up = le.estimate_light(t, color, EstimationParams(), up=np.array([0.0, 1.0, 0.0]))
        assert with_up.horizon_prior_used
        d_free, d_up = sh.dominant_direction(free.sh), sh.dominant_direction(with_up.sh)
        assert d_up[1] > d_free[1]  # pulled up towards the horizon
        off = le.estimate_light(
            t, color, EstimationParams(horizon_prior=0.0), up=np.array([0.0, 1.0, 0.0])
        )
        assert not off.horizon_prior_used
