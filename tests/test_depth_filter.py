"""Depth filter chain D' / D'' / D''' (eq. 1-5 of seeds/000) and normals from depth.

Hand-made depth maps for every case of eq. 3, the edge-aligning and denoising passes, the
Numba kernels against the NumPy oracles, normals against analytic planes, extremes, input
validation, and the CUDA drivers (on a GPU when there is one, else in numba's simulator).
"""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from arlight.core.camera import PinholeCamera
from arlight.pipeline import depth_filter as df
from arlight.pipeline.color import intensity_from_rgb
from arlight.pipeline.config import Config

DARK, BRIGHT = 50.0, 200.0  # grey levels far apart compared with lambda_I = 7


def _flat(h, w, value, dtype=np.float32):
    return np.full((h, w), value, dtype)


def _random_inputs(seed, h=31, w=43, hole_fraction=0.35, agree_fraction=0.5):
    """Random depth with holes; D_v near D_c (some within lambda_D) on agree_fraction."""
    rng = np.random.default_rng(seed)
    dc = rng.uniform(0.3, 4.0, (h, w)).astype(np.float32)
    dc[rng.random((h, w)) < hole_fraction] = 0
    agree = rng.random((h, w)) < agree_fraction
    noise = rng.uniform(-0.06, 0.06, (h, w))
    dv = np.where(agree, dc + noise, rng.uniform(0.3, 4.0, (h, w)))
    dv = np.where(dv > 0.05, dv, 0).astype(np.float32)
    dv[rng.random((h, w)) < 0.25] = 0
    intensity = (rng.integers(0, 8, (h, w)) * 4.0).astype(np.float32)  # steps below and above 7
    return dc, dv, intensity


def _plane_depth(camera, normal, offset_m):
    """Depth of the plane n . X = -offset_m (n unit, facing the camera) at every pixel."""
    rays = camera.unproject(np.ones((camera.height, camera.width), np.float32)).astype(np.float64)
    return (-offset_m / (rays @ normal)).astype(np.float32)


class TestIntensity:
    def test_rec709_weights_on_8bit_values(self):
        color = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]]], np.uint8)
        grey = intensity_from_rgb(color)
        assert grey.dtype == np.float32 and grey.shape == (1, 4)
        np.testing.assert_allclose(grey[0], [54.213, 182.376, 18.411, 255.0], rtol=1e-5)

    def test_black_and_saturated(self):
        assert intensity_from_rgb(np.zeros((2, 3, 3), np.uint8)).max() == 0
        np.testing.assert_allclose(
            intensity_from_rgb(np.full((2, 3, 3), 255, np.uint8)), 255.0, rtol=1e-6
        )

    @pytest.mark.parametrize(
        "bad, message",
        [
            (np.zeros((4, 4), np.uint8), r"\(H, W, 3\)"),
            (np.zeros((4, 4, 4), np.uint8), r"\(H, W, 3\)"),
            (np.zeros((4, 4, 3), np.float32), "uint8"),
        ],
    )
    def test_rejects(self, bad, message):
        with pytest.raises(ValueError, match="color_rgb_u8.*" + message):
            intensity_from_rgb(bad)


class TestMergeDepth:
    """D' (eq. 3), one test per case."""

    def test_moved_region_taken_from_raw(self):
        dc = _flat(10, 10, 1.0)
        dv = _flat(10, 10, 1.0)
        dv[2:5, 2:5] = 2.0  # the volume still holds the old surface there
        out = df.merge_depth(dc, dv, _flat(10, 10, DARK))
        np.testing.assert_array_equal(out[2:5, 2:5], 1.0)

    def test_agreeing_region_taken_from_volume(self):
        dc = _flat(10, 10, 1.0)
        dv = _flat(10, 10, 1.03)  # within lambda_D = 5 cm: the volume is more trustworthy
        out = df.merge_depth(dc, dv, _flat(10, 10, DARK))
        np.testing.assert_array_equal(out, np.float32(1.03))

    def test_difference_equal_to_threshold_keeps_raw(self):
        dc, dv = _flat(1, 1, 1.0), _flat(1, 1, 1.25)
        out = df.merge_depth(dc, dv, _flat(1, 1, DARK), depth_threshold_m=0.25)
        assert out[0, 0] == 1.0  # strict "<" for agreement

    def test_raw_without_volume_kept(self):
        dc = _flat(6, 6, 1.0)
        out = df.merge_depth(dc, np.zeros_like(dc), _flat(6, 6, DARK))
        np.testing.assert_array_equal(out, dc)
        np.testing.assert_array_equal(df.merge_depth(dc, None, _flat(6, 6, DARK)), dc)

    def test_hole_filled_from_volume_when_support_agrees(self):
        dc = _flat(12, 12, 1.0)
        dc[5:7, 5:7] = 0
        dv = _flat(12, 12, 1.02)
        out = df.merge_depth(dc, dv, _flat(12, 12, DARK), window=5)
        np.testing.assert_array_equal(out[5:7, 5:7], np.float32(1.02))

    def test_hole_filled_by_raw_median_when_support_disagrees(self):
        dc = _flat(12, 12, 1.0)
        dc[:, 6:] = 1.2  # two raw surfaces; the hole's window sees more of the 1.0 one
        dc[6, 5] = 0
        dv = _flat(12, 12, 1.6)  # the volume lags behind: nothing agrees
        out = df.merge_depth(dc, dv, _flat(12, 12, DARK), window=5)
        # window rows 4..8, cols 3..7: 3 columns at 1.0 (minus the hole), 2 at 1.2
        assert out[6, 5] == np.float32(1.0)

    def test_hole_majority_boundary(self):
        # The hole sees 4 support pixels; exactly 2 agree with the volume -> D_v (>= half).
        dc = np.array([[1.0, 1.0, 0.0, 1.0, 1.0]], np.float32)
        dv = np.array([[1.01, 1.01, 1.02, 1.5, 1.5]], np.float32)
        out = df.merge_depth(dc, dv, _flat(1, 5, DARK), window=5)
        assert out[0, 2] == np.float32(1.02)
        dv[0, 1] = 1.5  # now 1 of 4 agrees -> lower median of 1.0, 1.0, 1.0, 1.0
        out = df.merge_depth(dc, dv, _flat(1, 5, DARK), window=5)
        assert out[0, 2] == np.float32(1.0)

    def test_hole_with_agreeing_support_but_no_volume_at_hole_takes_median(self):
        dc = np.array([[1.0, 1.1, 0.0, 1.2, 1.3]], np.float32)
        dv = np.array([[1.0, 1.1, 0.0, 1.2, 1.3]], np.float32)
        out = df.merge_depth(dc, dv, _flat(1, 5, DARK), window=5)
        assert out[0, 2] == np.float32(1.1)  # lower median of 1.0, 1.1, 1.2, 1.3

    def test_support_does_not_cross_intensity_edge(self):
        h, w = 20, 20
        intensity = _flat(h, w, BRIGHT)
        intensity[:, :6] = DARK
        dc = _flat(h, w, 2.0)
        dc[:, :6] = 1.0
        dc[8:12, 5] = 0  # holes on the dark side, next to the edge
        dc[8:12, 6] = 0  # holes on the bright side, next to the edge
        out = df.merge_depth(dc, None, intensity)
        np.testing.assert_array_equal(out[8:12, 5], 1.0)
        np.testing.assert_array_equal(out[8:12, 6], 2.0)
        # without the intensity gate the bright side (9 of 14 columns) would win
        ungated = df.merge_depth(dc, None, intensity, intensity_threshold=1e6)
        np.testing.assert_array_equal(ungated[8:12, 5], 2.0)

    def test_hole_without_support(self):
        dc = _flat(9, 9, 0.0)
        dc[0, 0] = 1.0
        dv = _flat(9, 9, 0.0)
        dv[6, 6] = 1.7
        out = df.merge_depth(dc, dv, _flat(9, 9, DARK), window=3)
        assert out[6, 6] == np.float32(1.7)  # no support: the volume's depth
        assert out[4, 4] == 0.0  # no support and no volume: stays missing
        assert out[1, 1] == 1.0  # the valid raw pixel is in its window: its median

    def test_support_of_other_intensity_only_counts_as_no_support(self):
        dc = _flat(5, 5, 1.0)
        dc[2, 2] = 0
        intensity = _flat(5, 5, DARK)
        intensity[2, 2] = BRIGHT
        assert df.merge_depth(dc, None, intensity)[2, 2] == 0.0
        dv = _flat(5, 5, 3.0)
        assert df.merge_depth(dc, dv, intensity)[2, 2] == np.float32(3.0)

    def test_nan_is_missing(self):
        dc = _flat(8, 8, 1.0)
        dc[3, 3] = np.nan
        dv = _flat(8, 8, np.nan)
        out = df.merge_depth(dc, dv, _flat(8, 8, DARK), window=3)
        assert out[3, 3] == 1.0 and np.isfinite(out).all()

    @pytest.mark.parametrize("seed, agree_fraction", [(0, 0.5), (1, 0.5), (2, 0.9), (3, 1.0)])
    def test_kernel_matches_reference(self, seed, agree_fraction):
        dc, dv, intensity = _random_inputs(seed, agree_fraction=agree_fraction)
        for window in (3, 20):
            out = df.merge_depth(dc, dv, intensity, window=window)
            ref = df._merge_depth_reference(dc, dv, intensity, window=window)
            np.testing.assert_array_equal(out, ref)


class TestJointBilateralMedian:
    """D'' (eq. 4)."""

    def test_subsampled_offsets(self):
        np.testing.assert_array_equal(df._window_offsets(8, 5), [-4, -2, 0, 1, 3])
        np.testing.assert_array_equal(df._window_offsets(8, 8), np.arange(-4, 4))
        np.testing.assert_array_equal(df._window_offsets(8, 20), np.arange(-4, 4))
        np.testing.assert_array_equal(df._window_offsets(20, 5), [-10, -5, 0, 4, 9])
        np.testing.assert_array_equal(df._window_offsets(7, 1), [0])
        np.testing.assert_array_equal(df._window_offsets(2), [-1, 0])

    @pytest.mark.parametrize("shift", [1, -1])
    def test_misregistered_edge_aligned_with_intensity_edge(self, shift):
        h, w = 16, 24
        intensity = _flat(h, w, DARK)
        intensity[:, 12:] = BRIGHT
        aligned = _flat(h, w, 2.0)
        aligned[:, 12:] = 1.0
        misregistered = np.roll(aligned, shift, axis=1)
        misregistered[:, 0], misregistered[:, -1] = 2.0, 1.0  # undo the roll's wrap-around
        assert (misregistered != aligned).sum() == h
        out = df.joint_bilateral_median(misregistered, intensity)
        np.testing.assert_array_equal(out, aligned)

    def test_misregistered_object_mostly_aligned(self):
        intensity = _flat(30, 30, DARK)
        intensity[10:20, 10:20] = BRIGHT
        aligned = _flat(30, 30, 2.0)
        aligned[10:20, 10:20] = 1.0
        misregistered = np.roll(aligned, (1, 1), axis=(0, 1))
        out = df.joint_bilateral_median(misregistered, intensity)
        assert (misregistered != aligned).sum() == 38
        assert (out != aligned).sum() <= 1  # only the corner, whose support is 5/9 wrong

    def test_fills_missing_pixel_from_its_support(self):
        depth = _flat(9, 9, 1.5)
        depth[4, 4] = 0
        out = df.joint_bilateral_median(depth, _flat(9, 9, DARK))
        assert out[4, 4] == np.float32(1.5)
        assert df.joint_bilateral_median(np.zeros((9, 9), np.float32), _flat(9, 9, DARK)).max() == 0

    @pytest.mark.parametrize("seed", [0, 1])
    def test_kernel_matches_reference(self, seed):
        dc, _, intensity = _random_inputs(seed)
        for window, subsample in ((8, 5), (5, 5), (9, 1), (4, 8)):
            out = df.joint_bilateral_median(dc, intensity, window, 7.0, subsample)
            ref = df._joint_bilateral_median_reference(dc, intensity, window, 7.0, subsample)
            np.testing.assert_array_equal(out, ref)


class TestMedianDepth:
    """D''' (eq. 5)."""

    def test_removes_salt_and_pepper(self):
        depth = _flat(20, 20, 1.0)
        spikes = [(3, 3), (3, 9), (8, 5), (12, 14), (17, 7)]
        for i, (y, x) in enumerate(spikes):
            depth[y, x] = 6.0 if i % 2 else 0.2
        depth[10, 10] = 0  # a missing pixel is filled too
        out = df.median_depth(depth)
        np.testing.assert_array_equal(out, 1.0)

    def test_window_offsets_and_empty_window(self):
        depth = np.zeros((3, 3), np.float32)
        depth[1, 1] = 2.0
        out = df.median_depth(depth)  # k = 2 looks at rows/cols -1..0
        expected = np.zeros((3, 3), np.float32)
        expected[1:, 1:] = 2.0
        np.testing.assert_array_equal(out, expected)

    @pytest.mark.parametrize("window", [1, 2, 3, 6])
    def test_kernel_matches_reference(self, window):
        dc, _, _ = _random_inputs(window)
        np.testing.assert_array_equal(
            df.median_depth(dc, window), df._median_depth_reference(dc, window)
        )


class TestFilterDepth:
    def test_passes_and_config(self):
        dc, dv, intensity = _random_inputs(5)
        config = Config()
        final, passes = df.filter_depth(dc, dv, intensity, config.filter)
        merged = df.merge_depth(dc, dv, intensity, 20, 7.0, 0.05)
        smoothed = df.joint_bilateral_median(merged, intensity, 8, 7.0, 5)
        np.testing.assert_array_equal(passes["merged"], merged)
        np.testing.assert_array_equal(passes["smoothed"], smoothed)
        np.testing.assert_array_equal(final, df.median_depth(smoothed, 2))
        np.testing.assert_array_equal(passes["denoised"], final)
        final, passes = df.filter_depth(dc, dv, intensity, Config.from_preset("mobile").filter)
        assert set(passes) == {"merged", "smoothed"}
        np.testing.assert_array_equal(final, smoothed)

    def test_each_pass_can_be_turned_off(self):
        """merge / smooth / denoise false: that pass hands its input on unchanged."""
        dc, dv, intensity = _random_inputs(6)
        raw = np.nan_to_num(dc.astype(np.float32))
        off = Config(device="CPU:0").replace(merge=False, smooth=False, denoise=False).filter
        final, passes = df.filter_depth(dc, dv, intensity, off)
        np.testing.assert_array_equal(final, raw)
        np.testing.assert_array_equal(passes["merged"], raw)
        only_smooth = Config().replace(merge=False, denoise=False).filter
        final, passes = df.filter_depth(dc, dv, intensity, only_smooth)
        np.testing.assert_array_equal(final, df.joint_bilateral_median(raw, intensity, 8, 7.0, 5))
        merged = df.merge_depth(dc, dv, intensity, 20, 7.0, 0.05)
        final, _ = df.filter_depth(
            dc, dv, intensity, Config().replace(smooth=False, denoise=False).filter
        )
        np.testing.assert_array_equal(final, merged)

    def test_all_missing_gives_zeros(self):
        zeros = np.zeros((24, 32), np.float32)
        final, passes = df.filter_depth(zeros, zeros, _flat(24, 32, DARK), Config().filter)
        for image in (final, *passes.values()):
            assert image.dtype == np.float32 and not image.any() and np.isfinite(image).all()
        nan = _flat(24, 32, np.nan)
        final, _ = df.filter_depth(nan, nan, _flat(24, 32, DARK), Config().filter)
        assert not final.any()

    def test_one_pixel(self):
        final, _ = df.filter_depth(
            _flat(1, 1, 1.5), _flat(1, 1, 1.52), _flat(1, 1, DARK), Config().filter
        )
        assert final.shape == (1, 1) and final[0, 0] == np.float32(1.52)
        final, _ = df.filter_depth(
            _flat(1, 1, 0.0), _flat(1, 1, 0.0), _flat(1, 1, DARK), Config().filter
        )
        assert final[0, 0] == 0

    @pytest.mark.parametrize("depth_m", [0.1, 10.0])
    def test_near_and_far_planes(self, depth_m):
        dc = _flat(40, 50, depth_m)
        dc[10:14, 20:30] = 0
        final, _ = df.filter_depth(dc, None, _flat(40, 50, DARK), Config().filter)
        np.testing.assert_array_equal(final, np.float32(depth_m))

    def test_cuda_config_without_gpu_raises(self):
        if df.cuda_available():
            pytest.skip("a GPU is present")
        with pytest.raises(RuntimeError, match="cuda"):
            df.filter_depth(
                _flat(2, 2, 1.0),
                None,
                _flat(2, 2, DARK),
                Config().filter,
                backend=df.backend_for_device(Config(device="CUDA:0").device),
            )


class TestNormals:
    camera = PinholeCamera.kinect_v1(64, 48)

    def test_fronto_parallel_plane(self):
        for depth_m in (0.1, 2.0, 10.0):
            normals = df.normals_from_depth(_flat(48, 64, depth_m), self.camera)
            assert normals.dtype == np.float32 and normals.shape == (48, 64, 3)
            np.testing.assert_allclose(normals.reshape(-1, 3), [[0, 0, -1]] * (48 * 64), atol=1e-6)

    @pytest.mark.parametrize("offset_m", [0.1, 1.5, 10.0])
    def test_tilted_plane(self, offset_m):
        normal = np.array([0.4, -0.3, -1.0])
        normal /= np.linalg.norm(normal)
        depth = _plane_depth(self.camera, normal, offset_m)
        normals = df.normals_from_depth(depth, self.camera)
        cos = np.clip(normals.reshape(-1, 3) @ normal, -1, 1)
        assert np.degrees(np.arccos(cos)).max() < 1.0

    def test_unit_and_facing_camera(self):
        normal = np.array([-0.5, 0.2, -1.0])
        normal /= np.linalg.norm(normal)
        depth = _plane_depth(self.camera, normal, 2.0)
        normals = df.normals_from_depth(depth, self.camera).astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
        points = self.camera.unproject(depth)
        assert ((normals * points).sum(-1) < 0).all()

    def test_step_edge_is_not_a_slope(self):
        depth = _flat(48, 64, 1.0)
        depth[:, 32:] = 1.5
        normals = df.normals_from_depth(depth, self.camera)
        np.testing.assert_allclose(normals.reshape(-1, 3), [[0, 0, -1]] * (48 * 64), atol=1e-6)

    def test_missing_and_isolated_pixels_are_zero(self):
        depth = np.zeros((48, 64), np.float32)
        depth[10, 10] = 1.0  # no neighbours
        depth[20, 20:30] = 1.0  # neighbours along x only
        normals = df.normals_from_depth(depth, self.camera)
        assert not normals.any() and np.isfinite(normals).all()
        depth = _flat(48, 64, 1.0)
        depth[5, 5] = np.nan
        normals = df.normals_from_depth(depth, self.camera)
        assert not normals[5, 5].any()
        np.testing.assert_allclose(normals[5, 6], [0, 0, -1], atol=1e-6)  # one-sided

    def test_one_pixel(self):
        normals = df.normals_from_depth(_flat(1, 1, 1.0), PinholeCamera.kinect_v1(1, 1))
        assert normals.shape == (1, 1, 3) and not normals.any()

    @pytest.mark.parametrize("seed", [0, 1])
    def test_kernel_matches_reference(self, seed):
        rng = np.random.default_rng(seed)
        normal = rng.normal(size=3)
        normal[2] = -abs(normal[2]) - 1.0
        normal /= np.linalg.norm(normal)
        depth = _plane_depth(self.camera, normal, 1.0)
        depth *= (1 + rng.normal(0, 0.01, depth.shape)).astype(np.float32)  # some jumps
        depth[rng.random(depth.shape) < 0.2] = 0
        depth[:, 40:] *= 1.3
        np.testing.assert_allclose(
            df.normals_from_depth(depth, self.camera),
            df._normals_from_depth_reference(depth, self.camera),
            atol=1e-5,
        )


class TestValidation:
    def test_shape_mismatch_names_argument(self):
        dc = _flat(4, 5, 1.0)
        with pytest.raises(
            ValueError,
            match=r"depth_volume_m: expected shape \(4, 5\).*"
            r"got \(5, 4\)",
        ):
            df.merge_depth(dc, _flat(5, 4, 1.0), _flat(4, 5, DARK))
        with pytest.raises(ValueError, match=r"intensity: expected shape \(4, 5\)"):
            df.merge_depth(dc, dc, _flat(4, 4, DARK))
        with pytest.raises(ValueError, match=r"depth_raw_m: expected shape \(H, W\)"):
            df.merge_depth(np.zeros((4, 5, 1), np.float32), dc, _flat(4, 5, DARK))
        with pytest.raises(ValueError, match=r"depth_m: expected shape \(48, 64\)"):
            df.normals_from_depth(dc, PinholeCamera.kinect_v1(64, 48))

    def test_bad_values(self):
        dc = _flat(4, 5, 1.0)
        grey = _flat(4, 5, DARK)
        with pytest.raises(ValueError, match="depth_raw_m: expected a float dtype"):
            df.merge_depth(np.ones((4, 5), np.uint16), dc, grey)
        for bad in (np.inf, -1.0):
            d = dc.copy()
            d[1, 1] = bad
            with pytest.raises(ValueError, match="depth_m: depth must be finite and >= 0"):
                df.median_depth(d)
        with pytest.raises(ValueError, match="intensity: expected finite"):
            df.joint_bilateral_median(dc, _flat(4, 5, np.nan))
        for window in (0, df.MAX_WINDOW + 1):
            with pytest.raises(ValueError, match=r"window: expected an integer in 1\.\.64"):
                df.merge_depth(dc, dc, grey, window=window)
        with pytest.raises(ValueError, match="subsample: expected an integer in 1"):
            df.joint_bilateral_median(dc, grey, subsample=2.5)
        with pytest.raises(ValueError, match="depth_threshold_m: expected a finite"):
            df.merge_depth(dc, dc, grey, depth_threshold_m=float("nan"))
        with pytest.raises(ValueError, match="backend must be one of"):
            df.median_depth(dc, backend="opencl")

    def test_float64_and_non_contiguous_inputs(self):
        dc, dv, intensity = _random_inputs(9)
        out = df.merge_depth(dc.astype(np.float64).T, dv.T.copy(), intensity.T)
        np.testing.assert_array_equal(
            out, df.merge_depth(dc.T.copy(), dv.T.copy(), intensity.T.copy())
        )


_CUDA_CHECK = textwrap.dedent("""
    import numpy as np
    from arlight.pipeline import depth_filter as df
    from arlight.core.camera import PinholeCamera

    rng = np.random.default_rng(3)
    h, w = {h}, {w}
    dc = rng.uniform(0.5, 3.0, (h, w)).astype(np.float32)
    dc[rng.random((h, w)) < 0.4] = 0
    dv = np.where(rng.random((h, w)) < 0.5, dc + 0.01, 2.0).astype(np.float32)
    grey = (rng.integers(0, 6, (h, w)) * 5).astype(np.float32)
    camera = PinholeCamera.kinect_v1(w, h)
    assert df.cuda_available()
    results = {{}}
    for backend in ("cpu", "cuda"):
        m = df.merge_depth(dc, dv, grey, backend=backend)
        s = df.joint_bilateral_median(m, grey, backend=backend)
        d = df.median_depth(s, backend=backend)
        plane = np.full((h, w), 1.0, np.float32) + np.arange(w, dtype=np.float32) * 0.01
        n = df.normals_from_depth(plane, camera, backend=backend)
        results[backend] = (m, s, d, n)
    for name, a, b in zip("msdn", results["cpu"], results["cuda"]):
        if name == "n":
            np.testing.assert_allclose(a, b, atol=1e-5)
        else:
            np.testing.assert_array_equal(a, b)
    print("CUDA == CPU")
""")


class TestCuda:
    @pytest.mark.skipif(not df.cuda_available(), reason="no CUDA GPU visible to numba")
    def test_gpu_matches_cpu(self):
        exec(_CUDA_CHECK.format(h=480, w=640), {})

    def test_kernels_in_cuda_simulator_match_cpu(self):
        """The CUDA drivers run (as Python) in numba's simulator and match the CPU drivers."""
        env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
        result = subprocess.run(
            [sys.executable, "-c", _CUDA_CHECK.format(h=9, w=13)],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        assert "CUDA == CPU" in result.stdout

    def test_cuda_backend_without_gpu_raises(self):
        if df.cuda_available():
            pytest.skip("a GPU is present")
        with pytest.raises(RuntimeError, match="backend='cuda'"):
            df.merge_depth(_flat(2, 2, 1.0), None, _flat(2, 2, DARK), backend="cuda")
