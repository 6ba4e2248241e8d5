"""SH library: orthonormality, known values, projection, rotation, irradiance, layouts."""

import math

import numpy as np
import pytest

from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


class TestBasis:
    @pytest.mark.parametrize("bands", [1, 4, 8, 12])
    def test_orthonormal_by_quadrature(self, bands):
        dirs = sh.fibonacci_sphere(40000)
        y = sh.sh_basis(dirs, bands)
        gram = y.T @ y * (4 * math.pi / len(dirs))
        assert np.abs(gram - np.eye(bands * bands)).max() < 2e-3

    def test_first_bands_written_out(self):
        rng = np.random.default_rng(1)
        d = rng.normal(size=(50, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        x, y, z = d.T
        expected = np.stack(
            [
                np.full_like(x, 0.28209479177387814),
                0.4886025119029199 * y,
                0.4886025119029199 * z,
                0.4886025119029199 * x,
                1.0925484305920792 * x * y,
                1.0925484305920792 * y * z,
                0.31539156525252005 * (3 * z * z - 1),
                1.0925484305920792 * x * z,
                0.5462742152960396 * (x * x - y * y),
                0.5900435899266435 * y * (3 * x * x - y * y),
                2.890611442640554 * x * y * z,
                0.4570457994644658 * y * (5 * z * z - 1),
                0.3731763325901154 * z * (5 * z * z - 3),
                0.4570457994644658 * x * (5 * z * z - 1),
                1.445305721320277 * z * (x * x - y * y),
                0.5900435899266435 * x * (x * x - 3 * y * y),
            ],
            axis=-1,
        )
        np.testing.assert_allclose(sh.sh_basis(d, 4), expected, atol=1e-12)

    def test_poles_and_zero_vector_are_finite(self):
        out = sh.sh_basis(np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 0.0]]), 12)
        assert np.all(np.isfinite(out))

    def test_sloan_phase_toggle(self):
        c = np.arange(16, dtype=float)
        t = sh.toggle_condon_shortley(c)
        assert list(np.nonzero(t != c)[0]) == [1, 3, 5, 7, 9, 11, 13, 15]
        np.testing.assert_array_equal(sh.toggle_condon_shortley(t), c)


class TestProjection:
    def test_project_then_evaluate_band_limited(self):
        rng = np.random.default_rng(2)
        c = rng.normal(size=16)
        got = sh.project(lambda d: sh.evaluate(c, d), 4, samples=40000)
        np.testing.assert_allclose(got, c, atol=2e-3)

    def test_constant_function(self):
        got = sh.project(lambda d: np.full(len(d), 2.0), 3)
        assert got[0] == pytest.approx(2.0 * math.sqrt(4 * math.pi), rel=1e-6)
        assert np.abs(got[1:]).max() < 1e-4

    @pytest.mark.parametrize("seed", range(5))
    def test_directional_light_recovered_within_1_degree(self, seed):
        rng = np.random.default_rng(seed)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        # a narrow lobe (cos^200) plus a dim uniform sky, projected numerically
        lobe = lambda w: np.maximum(0.0, w @ d) ** 200 + 0.05  # noqa: E731
        c = sh.project(lobe, 4, samples=80000)
        got, intensity = sh.dominant_light(c)
        angle = angular_error_deg(got, d)
        assert angle < 1.0
        assert intensity > 0

    def test_delta_light_intensity(self):
        d = np.array([0.3, -0.5, 0.8])
        d /= np.linalg.norm(d)
        c = sh.directional_light(d, 3.0, 4)
        got, intensity = sh.dominant_light(c)
        np.testing.assert_allclose(got, d, atol=1e-12)
        assert intensity == pytest.approx(3.0)


class TestRotation:
    def test_rotation_consistent_with_rotating_directions(self):
        rng = np.random.default_rng(3)
        c = rng.normal(size=25)
        r = _random_rotation(rng)
        rotated = sh.rotate(c, r)
        dirs = sh.fibonacci_sphere(200)
        # f'(w) = f(R^T w)
        np.testing.assert_allclose(sh.evaluate(rotated, dirs), sh.evaluate(c, dirs @ r), atol=1e-9)

    def test_rotation_moves_dominant_direction(self):
        rng = np.random.default_rng(4)
        r = _random_rotation(rng)
        d = np.array([0.0, 0.6, 0.8])
        c = sh.directional_light(d, 1.0, 4)
        np.testing.assert_allclose(sh.dominant_direction(sh.rotate(c, r)), r @ d, atol=1e-9)

    def test_compose_and_invert(self):
        rng = np.random.default_rng(5)
        a, b = _random_rotation(rng), _random_rotation(rng)
        m = sh.rotation_matrix
        np.testing.assert_allclose(m(a, 4) @ m(b, 4), m(a @ b, 4), atol=1e-9)
        np.testing.assert_allclose(m(a, 4) @ m(a.T, 4), np.eye(16), atol=1e-9)


class TestIrradiance:
    def test_band_factors(self):
        a = sh.lambert_band_factors(5)
        np.testing.assert_allclose(a, [math.pi, 2 * math.pi / 3, math.pi / 4, 0, -math.pi / 24])

    def test_matches_numerical_cosine_integral(self):
        rng = np.random.default_rng(6)
        c = rng.normal(size=9) * 0.1
        c[0] = 2.0
        e = sh.irradiance_from_radiance(c)
        dirs = sh.fibonacci_sphere(60000)
        radiance = sh.evaluate(c, dirs)
        for n in rng.normal(size=(4, 3)):
            n /= np.linalg.norm(n)
            numeric = np.sum(radiance * np.maximum(0, dirs @ n)) * 4 * math.pi / len(dirs)
            assert sh.evaluate(e, n[None])[0] == pytest.approx(numeric, rel=2e-3)


class TestLayouts:
    def test_arcore_interleaved_and_planar(self):
        c = np.arange(48, dtype=float).reshape(3, 16)
        inter = sh.to_arcore_27(c)
        planar = sh.to_planar_27(c)
        assert len(inter) == len(planar) == 27
        assert inter[:6] == [0.0, 16.0, 32.0, -1.0, -17.0, -33.0]  # ARCore: CS phase
        assert planar[:3] == [0.0, 1.0, 2.0] and planar[9] == 16.0

    def test_gl_frame_flips_y_and_z(self):
        c = np.stack([sh.directional_light(np.array([0.0, 1.0, 0.0]), 1.0, 3)] * 3)
        out = np.array(sh.to_planar_27(c, rotation=sh.GL_FROM_CV)).reshape(3, 9)
        np.testing.assert_allclose(sh.dominant_direction(out[0]), [0, -1, 0], atol=1e-9)

    def test_bad_shape(self):
        with pytest.raises(ValueError, match="shape"):
            sh.to_arcore_27(np.zeros((3, 4)))


class TestAboveHorizonDirection:
    """sh.above_horizon_direction: the dominant direction of the light above the horizon."""

    @staticmethod
    def _sky(sun_elevation_deg: float, glow: float, up=(0.0, 1.0, 0.0)):
        """A sky (bright lobe at the sun's elevation + even blue) above the horizon of `up`,
        a uniform ground glow below: (SH bands 0..3, moment of the part above, up)."""
        up = np.asarray(up, float)
        e = math.radians(sun_elevation_deg)
        helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
        side = np.cross(up, helper)
        side /= np.linalg.norm(side)
        sun = math.cos(e) * side + math.sin(e) * up

        def radiance(w):
            above = w @ up > 0
            lobe = np.exp(8.0 * (w @ sun - 1.0))
            return np.where(above, 0.3 + 4.0 * lobe, glow)

        dirs = sh.fibonacci_sphere(60000)
        values = radiance(dirs)
        above = dirs @ up > 0
        moment = (values[above][:, None] * dirs[above]).sum(axis=0)
        return sh.project(radiance, 4, 60000), moment / np.linalg.norm(moment), up

    @pytest.mark.parametrize("elevation", [15.0, 40.0, 70.0])
    @pytest.mark.parametrize("glow", [0.0, 0.3, 1.0])
    def test_the_glow_below_does_not_move_it(self, elevation, glow):
        coeffs, truth, up = self._sky(elevation, glow)
        d = sh.above_horizon_direction(coeffs, up)
        assert angular_error_deg(d, truth) < 6.0
        # what it corrects: the whole-sphere moment sinks towards the horizon with the glow
        if glow >= 0.3:
            whole = sh.dominant_direction(coeffs)
            assert whole @ up < d @ up

    def test_follows_a_tilted_support_plane(self):
        up = np.array([0.3, 0.9, -0.2])
        coeffs, truth, up = self._sky(35.0, 0.5, up / np.linalg.norm(up))
        d = sh.above_horizon_direction(coeffs, up)
        assert angular_error_deg(d, truth) < 6.0

    def test_no_first_band_is_no_direction(self):
        assert not np.any(sh.above_horizon_direction(np.array([1.0]), np.array([0, 1.0, 0])))
        assert not np.any(
            sh.above_horizon_direction(np.r_[1.0, np.zeros(8)], np.array([0, 1.0, 0]))
        )
        assert not np.any(sh.above_horizon_direction(np.zeros(16), np.array([0, 1.0, 0])))


@pytest.mark.parametrize("count", [1, 4, 9, 16, 25])
def test_irradiance_as_a_quadratic_form_is_the_basis_sum(count):
    rng = np.random.default_rng(count)
    coeffs = rng.normal(size=count)
    normals = rng.normal(size=(500, 3)).astype(np.float32)
    want = sh.evaluate(sh.irradiance_from_radiance(coeffs), normals)
    np.testing.assert_allclose(sh.irradiance_at(coeffs, normals), want, atol=1e-12)
    # a sky from straight up: E(n) = pi / 4 (1 + cos)^2-like, brightest facing up
    sky = sh.project(lambda d: (d[:, 2] > 0).astype(float), 4)
    up, down = sh.irradiance_at(sky, np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert up > 2.5 and abs(down) < 0.2
