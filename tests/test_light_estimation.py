"""Light estimation T l = I (section 5.2 of seeds/000) and its temporal filter.

Synthetic transfer: random unit normals on the sphere with the visibility-free transfer
A_l Y_lm(n) (what radiance transfer gives without occlusion), and I = T l_true. Recovery with
and without noise, per-segment albedo, outliers, a single plane (rank-deficient), too few
samples, clipped and NaN pixels, RGB, the sRGB decode, and the temporal filter.
"""

import dataclasses
import math

import numpy as np
import pytest

from arlight.core.frames import Confidence
from arlight.evaluation import angular_error_deg
from arlight.pipeline import color, sh
from arlight.pipeline import light_confidence as lc
from arlight.pipeline import light_estimation as le
from arlight.pipeline.config import EstimationParams, TemporalParams
from arlight.pipeline.temporal_filter import TemporalFilter

LAMBERT_PER_COEFF = np.repeat(sh.lambert_band_factors(4), [1, 3, 5, 7])
LIGHT_DIR = (0.3, -0.8, 0.5)
# The default regularisation (4e-3) damps bands 2-3 hard: on real frames that is what holds
# the direction (docs/results/accuracy.md), on the ideal point lights of these tests it costs a
# few per cent of band-1 magnitude. Tests of exact recovery use a weak one.
WEAK = EstimationParams(regularization=1e-3)
# the alternation run to its fixed point under a regularisation too weak to bias it
CONVERGED = EstimationParams(regularization=1e-4)
# the Huber re-weighting of the relative residual (off by default: decision 0052)
HUBER = EstimationParams(robust_threshold=1.345, robust_iterations=8)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _light(direction=LIGHT_DIR, intensity=0.6, ambient=0.3):
    """Radiance SH (16,): a delta light of `intensity` plus a constant `ambient` term."""
    coeffs = sh.directional_light(_unit(direction), intensity, 4)
    coeffs[0] += ambient
    return coeffs


def _synthetic(m=3000, seed=0):
    """Random unit normals (m, 3) and their visibility-free transfer (m, 16)."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n, sh.sh_basis(n, 4) * LAMBERT_PER_COEFF


def _grey(intensity):
    return np.repeat(np.asarray(intensity, dtype=np.float64)[:, None], 3, axis=1)


def _angle_deg(a, b):
    """Degrees between the dominant directions of two SH vectors."""
    return angular_error_deg(sh.dominant_direction(a), sh.dominant_direction(b))


class TestSrgb:
    def test_known_values(self):
        lin = color.srgb_to_linear(np.array([0, 10, 128, 255], np.uint8))
        assert lin.dtype == np.float32
        np.testing.assert_allclose(
            lin, [0.0, 10 / 255 / 12.92, 0.21586050, 1.0], rtol=1e-6, atol=1e-9
        )

    def test_monotonic_and_shape_kept(self):
        img = np.arange(256, dtype=np.uint8).reshape(16, 16)[..., None].repeat(3, axis=2)
        lin = color.srgb_to_linear(img)
        assert lin.shape == (16, 16, 3)
        assert np.all(np.diff(lin[..., 0].reshape(-1)) > 0)


class TestRecovery:
    def test_exact_data(self):
        _, t = _synthetic()
        light = _light()
        est = le.estimate_light(t, _grey(t @ light), WEAK)
        assert _angle_deg(est.sh, light) < 1.0
        # A_3 = 0: band 3 is invisible to a diffuse surface and is not invented
        assert est.confidence.bands_estimated == 3
        np.testing.assert_array_equal(est.sh[9:], 0.0)
        np.testing.assert_allclose(est.sh[:4], light[:4], rtol=0.02, atol=2e-3)
        assert est.confidence.samples == 3000 and est.confidence.value > 0
        assert est.confidence.condition_number < 10
        assert est.sh_rgb is None

    def test_default_regularisation_keeps_direction_and_most_of_the_magnitude(self):
        _, t = _synthetic()
        light = _light()
        est = le.estimate_light(t, _grey(t @ light), EstimationParams())
        assert _angle_deg(est.sh, light) < 1.0
        np.testing.assert_allclose(est.sh[:4], light[:4], rtol=0.15)

    @pytest.mark.parametrize("seed", [1, 2])
    def test_noisy_data(self, seed):
        _, t = _synthetic(seed=seed)
        light = _light((-0.2, 0.4, 0.9))
        rng = np.random.default_rng(seed + 10)
        noisy = (t @ light) * (1.0 + 0.05 * rng.normal(size=len(t))) + 0.005 * rng.normal(
            size=len(t)
        )
        est = le.estimate_light(t, _grey(noisy), EstimationParams())
        assert _angle_deg(est.sh, light) < 1.0
        assert np.all(np.isfinite(est.sh)) and est.residual_rel < 0.2

    def test_frame_follows_transfer(self):
        # T in a rotated frame gives the light in that frame
        _, t = _synthetic()
        light = _light()
        rot = sh.rotation_matrix(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), 4)
        est = le.estimate_light(t @ rot.T, _grey(t @ light), EstimationParams())
        # T' l' = T l with T' = T R^T  <=>  l' = R l
        assert _angle_deg(est.sh, rot @ light) < 1.0


class TestAlbedoSegments:
    ALBEDO = np.array([0.2, 0.5, 0.8])

    def test_segments_recover_direction(self):
        # three materials on three latitude bands of the normals (top, middle, bottom of
        # an object): the unknown albedo is correlated with the normal, as in real scenes
        n, t = _synthetic()
        light = _light()
        segments = np.digitize(n[:, 2], [-1 / 3, 1 / 3])
        color = _grey((t @ light) * self.ALBEDO[segments])
        with_segments = le.estimate_light(t, color, CONVERGED, segments=segments)
        without = le.estimate_light(t, color, CONVERGED)
        assert _angle_deg(with_segments.sh, light) < 3.0
        assert _angle_deg(without.sh, light) > 10.0
        assert with_segments.residual_rel < without.residual_rel

    @pytest.mark.parametrize("layout", ["azimuth", "latitude", "x"])
    @pytest.mark.parametrize("direction", [LIGHT_DIR, (-0.5, 0.5, -0.7)])
    def test_alternation_converges_to_exact_solution(self, layout, direction):
        # the model I = a_g T l is identifiable: with many alternations and almost no
        # regularisation the exact light comes back for any layout
        n, t = _synthetic()
        light = _light(direction)
        segments = {
            "azimuth": np.digitize(np.arctan2(n[:, 1], n[:, 0]), [-1.05, 1.05]),
            "latitude": np.digitize(n[:, 2], [-1 / 3, 1 / 3]),
            "x": np.digitize(n[:, 0], [-1 / 3, 1 / 3]),
        }[layout]
        color = _grey((t @ light) * self.ALBEDO[segments])
        cfg = EstimationParams(robust_iterations=60, regularization=1e-6)
        est = le.estimate_light(t, color, cfg, segments=segments)
        assert _angle_deg(est.sh, light) < 0.5

    def test_default_passes_reach_the_fixed_point(self):
        # the alternation converges slowly; the default's passes get where many more do
        n, t = _synthetic()
        light = _light()
        segments = np.digitize(np.arctan2(n[:, 1], n[:, 0]), [-1.05, 1.05])
        color = _grey((t @ light) * self.ALBEDO[segments])
        default = le.estimate_light(t, color, EstimationParams(), segments=segments)
        many = le.estimate_light(
            t, color, EstimationParams(robust_iterations=200), segments=segments
        )
        short = le.estimate_light(
            t, color, EstimationParams(robust_iterations=4), segments=segments
        )
        assert _angle_deg(default.sh, many.sh) < 0.5
        assert _angle_deg(short.sh, many.sh) > 2.0  # so the passes matter here

    @pytest.mark.xfail(
        strict=True,
        reason="known limitation: at its fixed point the alternation under the default "
        "regularisation is biased by it, 11-13 degrees for segments split by latitude or x",
    )
    def test_default_config_any_layout(self):
        n, t = _synthetic()
        light = _light()
        segments = np.digitize(n[:, 2], [-1 / 3, 1 / 3])
        color = _grey((t @ light) * self.ALBEDO[segments])
        est = le.estimate_light(t, color, EstimationParams(), segments=segments)
        assert _angle_deg(est.sh, light) < 3.0


class TestOutliers:
    def _data(self):
        n, t = _synthetic()
        light = _light(intensity=0.2, ambient=0.1)  # dim enough that 3x is not clipped
        return n, t, light, t @ light

    def test_robust_beats_plain_least_squares(self):
        _, t, light, clean = self._data()
        bad = clean.copy()
        idx = np.random.default_rng(3).choice(len(bad), len(bad) // 10, replace=False)
        bad[idx] *= 3.0
        assert bad.max() < le.CLIP_LEVEL  # the outliers are not simply clipped away
        robust = le.estimate_light(t, _grey(bad), HUBER)
        plain = le.estimate_light(t, _grey(bad), EstimationParams(robust_iterations=0))
        assert robust.confidence.samples == plain.confidence.samples == len(bad)
        e_robust, e_plain = _angle_deg(robust.sh, light), _angle_deg(plain.sh, light)
        assert e_robust < e_plain and e_robust < 1.5
        # the scale comes back too: band 0 near the truth, not inflated by the outliers
        assert robust.sh[0] == pytest.approx(light[0], rel=0.05)
        assert abs(robust.sh[0] - light[0]) < abs(plain.sh[0] - light[0])

    def test_clustered_outliers(self):
        """A bright patch (x3) is down-weighted: residuals are relative to the prediction."""
        n, t, light, clean = self._data()
        bad = clean.copy()
        idx = np.argsort(-(n @ _unit([-0.6, 0.2, 0.3])))[: len(bad) // 10]  # one bright patch
        bad[idx] *= 3.0
        robust = le.estimate_light(t, _grey(bad), HUBER)
        plain = le.estimate_light(t, _grey(bad), EstimationParams(robust_iterations=0))
        assert _angle_deg(robust.sh, light) < _angle_deg(plain.sh, light)

    def test_default_keeps_every_weight(self):
        """Off by default, the re-weighting leaves every sample its weight; on, it lowers
        the outliers' (and only theirs, mostly)."""
        _, t, _, clean = self._data()
        bad = clean.copy()
        idx = np.random.default_rng(3).choice(len(bad), len(bad) // 10, replace=False)
        bad[idx] *= 3.0
        default = le.estimate_light(t, _grey(bad), EstimationParams())
        huber = le.estimate_light(t, _grey(bad), HUBER)
        assert default.fit is not None and huber.fit is not None
        np.testing.assert_array_equal(default.fit.weights, 1.0)
        outlier = np.zeros(len(bad), bool)
        outlier[idx] = True
        assert np.median(huber.fit.weights[outlier]) < 0.5
        assert np.median(huber.fit.weights[~outlier]) == 1.0


class TestDegenerate:
    def test_single_plane_rank_deficient(self):
        # every pixel has the same normal: only one combination of coefficients is seen
        m = 1000
        t = np.repeat(sh.sh_basis(_unit([0.0, -1.0, 0.2]), 4)[None] * LAMBERT_PER_COEFF, m, 0)
        light = _light()
        rng = np.random.default_rng(0)
        color = _grey((t @ light) * (1.0 + 0.01 * rng.normal(size=m)))
        est = le.estimate_light(t, color, dataclasses.replace(WEAK, estimate_rgb=True))
        conf = est.confidence
        assert conf.bands_estimated < 4 or conf.condition_number > le.MAX_CONDITION
        assert conf.bands_estimated == 1  # no band-1 direction is invented from one normal
        assert np.all(np.isfinite(est.sh)) and np.all(np.isfinite(est.sh_rgb))
        assert np.isfinite(conf.value) and 0.0 <= conf.value <= 1.0
        assert np.isfinite(est.residual_rel)
        np.testing.assert_array_equal(sh.dominant_direction(est.sh), 0.0)

    @pytest.mark.parametrize("rgb", [False, True])
    def test_too_few_samples(self, rgb):
        _, t = _synthetic(m=150)
        est = le.estimate_light(
            t, _grey(t @ _light()), EstimationParams(min_samples=200, estimate_rgb=rgb)
        )
        assert est.confidence.value == 0.0 and est.confidence.samples == 150
        assert "min_samples" in est.confidence.reason
        np.testing.assert_array_equal(est.sh, np.zeros(16))
        if rgb:
            np.testing.assert_array_equal(est.sh_rgb, np.zeros((3, 16)))
        else:
            assert est.sh_rgb is None

    def test_empty_input(self):
        est = le.estimate_light(np.zeros((0, 16)), np.zeros((0, 3)), EstimationParams())
        assert est.confidence.value == 0.0 and est.confidence.samples == 0
        assert np.all(est.sh == 0)

    def test_clipped_dark_and_nan_pixels_excluded(self):
        _, t = _synthetic(m=2000)
        light = _light()
        color = _grey(t @ light)
        rng = np.random.default_rng(1)
        bad_t = rng.normal(size=(400, 16))
        bad_color = rng.uniform(0.1, 0.9, (400, 3))
        bad_color[:100, 0] = 0.99  # one clipped channel
        bad_color[100:150] = np.nan
        bad_color[150:200, 1] = np.inf
        bad_t[200:250, 5] = np.nan
        bad_color[250:300] = 0.001  # too dark to carry signal
        bad_t[300:] = 0.0  # no transfer (fully occluded)
        order = rng.permutation(2400)
        t_all = np.concatenate([t, bad_t])[order]
        color_all = np.concatenate([color, bad_color])[order]
        cfg = EstimationParams(estimate_rgb=True)
        mixed = le.estimate_light(t_all, color_all, cfg)
        clean = le.estimate_light(t, color, cfg)
        assert mixed.confidence.samples == 2000
        np.testing.assert_allclose(mixed.sh, clean.sh, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(mixed.sh_rgb, clean.sh_rgb, rtol=1e-8, atol=1e-10)
        assert _angle_deg(mixed.sh, light) < 1.0


class TestRgb:
    def test_rgb_channels_and_luminance(self):
        _, t = _synthetic()
        base = _light(intensity=0.5, ambient=0.25)
        warm = np.stack([1.0 * base, 0.85 * base, 0.6 * base])
        warm[2, 0] += 0.05  # a bluish ambient
        color = t @ warm.T
        est = le.estimate_light(t, color, dataclasses.replace(WEAK, estimate_rgb=True))
        assert est.sh_rgb.shape == (3, 16)
        np.testing.assert_allclose(le.LUMA @ est.sh_rgb, est.sh, atol=1e-9)
        for ch in range(3):
            assert _angle_deg(est.sh_rgb[ch], warm[ch]) < 1.0
            assert est.sh_rgb[ch, 0] == pytest.approx(warm[ch, 0], rel=0.02)


class TestTemporalFilter:
    OLD = _light((0.0, 0.0, 1.0))
    NEW = _light((1.0, 0.0, 0.0))  # 90 degrees away

    def _filter(self):
        return TemporalFilter(TemporalParams())

    def test_constant_input_converges_immediately(self):
        f = self._filter()
        for _ in range(4):
            np.testing.assert_allclose(f.update(self.OLD, 0.8), self.OLD, atol=1e-12)

    def test_follows_a_light_change_within_three_frames(self):
        f = self._filter()
        for _ in range(5):
            f.update(self.OLD, 0.8)
        for _ in range(3):
            state = f.update(self.NEW, 0.8)
        assert _angle_deg(state, self.NEW) < 10.0

    def test_single_outlier_frame_does_not_reset(self):
        f = self._filter()
        for _ in range(5):
            f.update(self.OLD, 0.8)
        after_outlier = f.update(self.NEW, 0.8)
        assert _angle_deg(after_outlier, self.OLD) < 30.0
        assert _angle_deg(after_outlier, self.OLD) < _angle_deg(after_outlier, self.NEW)
        for _ in range(3):
            state = f.update(self.OLD, 0.8)
        assert _angle_deg(state, self.OLD) < 10.0

    def test_zero_confidence_keeps_state(self):
        f = self._filter()
        unset = f.update(self.NEW, 0.0)  # nothing to keep yet: passes through, stores nothing
        np.testing.assert_array_equal(unset, self.NEW)
        assert f.state is None
        f.update(self.OLD, 0.8)
        for _ in range(3):
            kept = f.update(self.NEW, 0.0)
            np.testing.assert_array_equal(kept, self.OLD)
        np.testing.assert_array_equal(f.state, self.OLD)
        kept[0] = 123.0  # a copy is returned, the state is not aliased
        assert f.state[0] != 123.0

    def test_half_life_zero_is_no_filter(self):
        """Half-life 0 reports each frame's own estimate, whatever its confidence (a frame
        without one keeps the last); a tiny half-life still blends a frame of confidence
        below 0.5 with the last (its weight is scaled by the confidence)."""
        off = TemporalFilter(TemporalParams(temporal_half_life_frames=0.0))
        tiny = TemporalFilter(TemporalParams(temporal_half_life_frames=0.001))
        for f in (off, tiny):
            f.update(self.OLD, 0.8)
        np.testing.assert_array_equal(off.update(self.NEW, 0.05), self.NEW)
        np.testing.assert_array_equal(off.update(self.OLD, 0.0), self.NEW)  # no estimate
        blended = tiny.update(self.NEW, 0.05)
        assert 20.0 < _angle_deg(blended, self.NEW) < 70.0


class TestBounceTerm:
    def test_light_and_bounce_scale_recovered(self):
        _, t = _synthetic()
        rng = np.random.default_rng(3)
        bounce = rng.uniform(0.0, 2.0, len(t))
        light, beta = _light(), 0.12
        est = le.estimate_light(
            t, _grey(t @ light + beta * bounce), EstimationParams(), bounce=bounce
        )
        assert est.bounce_scale == pytest.approx(beta, rel=0.05)
        assert _angle_deg(est.sh, light) < 1.0
        # ignoring the bounce light biases the estimate
        ignored = le.estimate_light(t, _grey(t @ light + beta * bounce), EstimationParams())
        assert ignored.bounce_scale == 0.0

    def test_negative_bounce_scale_is_not_allowed(self):
        _, t = _synthetic()
        bounce = np.random.default_rng(4).uniform(0.0, 2.0, len(t))
        light = _light()
        est = le.estimate_light(
            t, _grey(np.maximum(t @ light - 0.1 * bounce, 0.01)), EstimationParams(), bounce=bounce
        )
        assert est.bounce_scale == 0.0


class TestConfidenceEvidence:
    """The confidence's factors: the spread of the normals, the horizon disagreement, and
    the causes its reason names (docs/results/confidence.md)."""

    def test_normal_spread_of_known_layouts(self):
        _, sphere = _synthetic(20000)
        assert le.normal_spread(sphere) == pytest.approx(1.0, abs=0.01)
        n = np.tile([[0.0, -1.0, 0.0]], (500, 1))  # a floor seen from above (y down)
        plane = sh.sh_basis(n, 4) * LAMBERT_PER_COEFF
        assert le.normal_spread(plane) == pytest.approx(0.0, abs=1e-9)
        up = _synthetic(20000)[0]
        up = up[up[:, 1] < 0]  # a hemisphere of normals: 1 - |mean|^2 = 1 - 1/4
        assert le.normal_spread(sh.sh_basis(up, 4)) == pytest.approx(0.75, abs=0.02)
        assert le.normal_spread(plane[:, :1]) == 0.0  # no band 1: nothing known

    def test_horizon_disagreement(self):
        up = np.array([0.0, -1.0, 0.0])
        sky = _light((0.0, -1.0, 0.2), ambient=0.0)  # above the horizon: they agree
        assert le.horizon_disagreement_deg(sky, up) < 5.0
        below = _light((0.3, 0.9, 0.1), ambient=0.0)  # a lobe below the horizon
        assert le.horizon_disagreement_deg(below, up) > 10.0 + le.horizon_disagreement_deg(sky, up)
        assert le.horizon_disagreement_deg(below, None) == 0.0

    def test_spread_and_horizon_rank_the_confidence(self):
        """One plane or light below the horizon: lower confidence, each cause named."""
        normals, t = _synthetic(40000)
        up = np.array([0.0, -1.0, 0.0])
        lit = _grey(t @ _light())
        wide = le.estimate_light(t, lit, WEAK, up=up)
        assert wide.confidence.normal_spread > 0.9 and wide.confidence.value >= lc.LOW_CONFIDENCE
        floor = normals[normals[:, 1] < -0.95]  # normals within 18 deg of up
        tf = sh.sh_basis(floor, 4) * LAMBERT_PER_COEFF
        narrow = le.estimate_light(tf, _grey(tf @ _light()), WEAK, up=up)
        assert narrow.confidence.value < wide.confidence.value
        assert narrow.confidence.value < lc.LOW_CONFIDENCE
        assert "few normal directions" in narrow.confidence.reason
        low = le.estimate_light(t, _grey(t @ _light((0.2, 0.95, 0.2))), WEAK, up=up)
        assert low.confidence.horizon_disagreement_deg > 10.0
        assert low.confidence.value < wide.confidence.value
        d = low.confidence.to_dict()
        assert d["normal_spread"] > 0.9 and d["horizon_disagreement_deg"] > 10.0

    def test_the_conditioning_factor_falls_over_the_range_fits_have(self):
        """Fits have condition numbers of 1e3-1e5 (decision 0065): the factor is 1 at 1e3
        and below, falls by 10^0.8 a decade, and stops at the floor."""
        f = lc.conditioning_factor
        assert f(1.0) == f(1e3) == 1.0
        assert f(1e4) == pytest.approx(10**-0.8) and f(1e5) == pytest.approx(10**-1.6)
        assert f(1e9) == lc.MIN_FACTOR
        values = [f(c) for c in np.logspace(3, 5, 9)]
        assert np.all(np.diff(values) < 0)  # strictly falling there

    def test_clipped_pixels_are_named(self):
        normals, t = _synthetic(40000)
        tf = t[normals[:, 1] < -0.95]
        rgb = _grey(tf @ _light())
        rgb[: len(rgb) // 4] = 1.0  # a quarter of the view saturated
        est = le.estimate_light(tf, rgb, WEAK)
        assert est.confidence.value < lc.LOW_CONFIDENCE
        assert "clipped (emitters" in est.confidence.reason


class TestViewAndSteadiness:
    """The factors the pipeline multiplies into a fit's confidence: side-facing normals and
    the jump from the last frames' direction."""

    def test_side_share_counts_normals_off_the_vertical(self):
        up = np.array([0.0, 1.0, 0.0])
        floor = np.tile(up, (30, 1))
        wall = np.tile([1.0, 0.0, 0.0], (10, 1))
        assert lc.side_share(floor, up) == 0.0
        assert lc.side_share(np.vstack([floor, wall]), up) == pytest.approx(0.25)
        assert lc.side_share(wall, None) is None
        assert lc.side_share(np.zeros((5, 3)), up) is None  # no normals

    def test_factors_multiply_and_are_named_when_low(self):
        conf = Confidence(samples=5000, condition_number=10.0, bands_estimated=4, value=0.8)
        same = lc.with_view_and_steadiness(conf, 0.5, 0.0)
        assert same.value == pytest.approx(0.8) and same.reason == ""
        assert same.to_dict()["side_share"] == 0.5
        ground = lc.with_view_and_steadiness(conf, 0.01, 0.0)
        assert ground.value == pytest.approx(0.8 * 0.01 / lc.SIDE_SHARE_FULL)
        assert "side-facing" in ground.reason
        jumped = lc.with_view_and_steadiness(conf, 0.5, 30.0)
        assert jumped.value == pytest.approx(0.8 * math.exp(-30.0 / lc.JUMP_SCALE_DEG))
        assert "jumped 30 deg" in jumped.reason and "side-facing" not in jumped.reason
        unknown = lc.with_view_and_steadiness(conf, None, 0.0)  # no plane yet: no view factor
        assert unknown.value == pytest.approx(0.8) and unknown.to_dict()["side_share"] is None
        # two fits of one frame (near the look-at point, the whole view) that disagree
        split = lc.with_view_and_steadiness(conf, 0.5, 0.0, 45.0)
        assert split.value == pytest.approx(0.8 * math.exp(-45.0 / lc.AGREE_SCALE_DEG))
        assert "45 deg from the one fitted over the whole view" in split.reason

    def test_no_estimate_stays_no_estimate(self):
        none = Confidence(reason="no valid depth")
        out = lc.with_view_and_steadiness(none, 0.5, 10.0)
        assert out.value == 0.0 and out.reason == "no valid depth"


def test_alternation_over_segment_sums_equals_the_per_sample_one():
    """Without re-weighting the alternation runs on each segment's Gram matrix and moments;
    a threshold too large to down-weight any sample runs the per-sample loop on the same
    model: the light, the bounce scale and the albedos agree to rounding."""
    n, t = _synthetic(4000, seed=5)
    rng = np.random.default_rng(5)
    segments = rng.integers(0, 12, len(n))
    segments[segments == 7] = 8  # a segment with no sample
    albedo = rng.uniform(0.1, 1.5, 12)
    bounce = rng.uniform(0.0, 0.2, len(n))
    color = _grey((t @ _light() + 0.4 * bounce) * albedo[segments])
    segment_sums = EstimationParams()
    per_sample = dataclasses.replace(segment_sums, robust_threshold=1e300)
    for b in (None, bounce):
        fast = le.estimate_light(t, color, segment_sums, segments=segments, bounce=b)
        slow = le.estimate_light(t, color, per_sample, segments=segments, bounce=b)
        np.testing.assert_allclose(fast.sh, slow.sh, rtol=1e-9, atol=1e-12)
        assert fast.bounce_scale == pytest.approx(slow.bounce_scale, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(fast.fit.albedo, slow.fit.albedo, rtol=1e-9, atol=1e-12)


def test_segment_grams_equal_the_direct_product():
    """SegmentGrams: sum_g a_g^2 G_g plus the down-weighted samples is A^T diag(w a^2) A."""
    from arlight.pipeline.light_estimation import SegmentGrams

    rng = np.random.default_rng(3)
    design = rng.normal(size=(2000, 17))
    labels = rng.integers(0, 9, 2000)
    labels[labels == 4] = 5  # a segment with no sample
    segment_albedo = rng.uniform(0.2, 2.0, 9)
    weights = np.where(rng.uniform(size=2000) < 0.3, rng.uniform(0.05, 1.0, 2000), 1.0)
    direct = design.T @ (design * (weights * segment_albedo[labels] ** 2)[:, None])
    np.testing.assert_allclose(
        SegmentGrams(design, labels)(segment_albedo, weights), direct, rtol=1e-10, atol=1e-9
    )
    plain = SegmentGrams(design, None)(np.ones(1), np.ones(2000))
    np.testing.assert_allclose(plain, design.T @ design, rtol=1e-12, atol=1e-9)
