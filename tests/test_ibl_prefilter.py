"""The fast 360 render path (issue 35, item 4): the packed mip pyramid, the prefiltered glossy
maps (pipeline/glossy_prefilter.py) against their NumPy oracle and against the per-pixel
kernel, and renders of the fast path against the per-pixel one.

Speed is measured by benchmarks/ibl_speed.py, not here.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from arlight.pipeline import equirect, glossy, glossy_prefilter, ibl_render
from arlight.pipeline.color import LUMA
from arlight.pipeline.ibl import diffuse_map_brute_force
from arlight.pipeline.virtual_scene import Material, VirtualScene
from arlight.sources.synthetic_panorama import synthetic_sky


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


def _random_directions(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def sky_pyramid() -> glossy.MipPyramid:
    return glossy.mip_pyramid(synthetic_sky(512))


class TestPackedPyramid:
    def test_bit_for_bit_the_chain_of_downsample_2x2(self):
        rng = np.random.default_rng(0)
        hdr = (rng.random((96, 192, 3)) ** 4 * 20).astype(np.float32)
        hdr[3, 5, 1], hdr[7, 9, 0], hdr[10, 11, 2] = np.nan, -2.0, np.inf
        pyr = glossy.mip_pyramid(hdr)
        level = np.maximum(np.nan_to_num(hdr, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
        heights = []
        for got in pyr.levels:
            np.testing.assert_array_equal(got, level)
            heights.append(level.shape[0])
            if level.shape[0] >= 2 and level.shape[0] % 2 == 0:
                level = glossy.downsample_2x2(level)
        assert heights == [96, 48, 24, 12, 6, 3]  # stops at the first odd height
        repacked = glossy.MipPyramid(pyr.levels)  # packed from the levels, the old way
        np.testing.assert_array_equal(repacked.data, pyr.data)
        np.testing.assert_array_equal(repacked.offsets, pyr.offsets)

    def test_float64_input_as_float32(self):
        hdr = synthetic_sky(64).astype(np.float64)
        pyr = glossy.mip_pyramid(hdr)
        assert pyr.data.dtype == np.float32
        np.testing.assert_array_equal(pyr.levels[0], hdr.astype(np.float32))


class TestPrefilteredMap:
    @pytest.mark.parametrize("roughness", [0.1, 0.2, 0.5])
    def test_texels_match_the_numpy_oracle(self, sky_pyramid, roughness):
        n = glossy.phong_exponent(roughness)
        got = glossy_prefilter.prefiltered_map(sky_pyramid, n)
        h = got.shape[0]
        assert got.shape == (h, 2 * h, 3) and h in sky_pyramid.heights
        assert math.pi / h <= glossy.lobe_radius_rad(n) / glossy_prefilter.TEXELS_PER_RADIUS
        step = 1 + (2 * h * h) // 30000  # the oracle's OpenCV lookups: < 32767 at a time
        centres = equirect.pixel_directions(h, 2 * h)[:, ::step].reshape(-1, 3)
        want = glossy.glossy_pattern_numpy(sky_pyramid, centres, roughness, frame="y")
        scale = float(np.abs(want).max())
        np.testing.assert_allclose(
            got[:, ::step].reshape(-1, 3), want, rtol=1e-4, atol=1e-5 * scale
        )

    def test_a_panorama_whose_height_is_not_a_power_of_two(self):
        pyr = glossy.mip_pyramid(synthetic_sky(960))  # levels 480, 240, 120, 60, 30, 15
        for rho in (0.1, 0.3):
            got = glossy_prefilter.prefiltered_map(pyr, glossy.phong_exponent(rho))
            h = got.shape[0]
            centres = equirect.pixel_directions(h, 2 * h)[:, :: 1 + (2 * h * h) // 30000]
            want = glossy.glossy_pattern_numpy(pyr, centres.reshape(-1, 3), rho, frame="y")
            sub = got[:, :: 1 + (2 * h * h) // 30000].reshape(-1, 3)
            np.testing.assert_allclose(sub, want, rtol=1e-4, atol=1e-5 * float(want.max()))

    def test_away_from_the_poles_the_same_as_the_per_pixel_kernel(self, sky_pyramid):
        # where |r.y| < 0.9 both use the frame about +y: the texels are the kernel's values
        n = glossy.phong_exponent(0.3)
        got = glossy_prefilter.prefiltered_map(sky_pyramid, n)
        centres = equirect.pixel_directions(got.shape[0], got.shape[1]).reshape(-1, 3)
        keep = np.abs(centres[:, 1]) < 0.9
        want = glossy.glossy(sky_pyramid, centres[keep], 0.3)
        np.testing.assert_allclose(
            got.reshape(-1, 3)[keep], want, rtol=1e-4, atol=1e-5 * float(want.max())
        )

    def test_constant_map_gives_its_value(self):
        pyr = glossy.mip_pyramid(np.full((128, 256, 3), 0.25, np.float32))
        for rho in (0.05, 0.5):
            got = glossy_prefilter.prefiltered_map(pyr, glossy.phong_exponent(rho))
            np.testing.assert_allclose(got, 0.25, rtol=1e-5)


class TestSpecular:
    def test_lookups_agree_with_the_per_pixel_kernel(self, sky_pyramid):
        # the median over the sphere within 0.5 %; near the sky's sun (10 000 times the
        # median radiance) the per-pixel pattern ripples as its rings cross the sun, which
        # the maps' interpolation smooths: there the test below judges both by the integral
        d = _random_directions(20000)
        for rho in (0.1, 0.2, 0.3, 0.5):
            n = glossy.phong_exponent(rho)
            modes = np.full(len(d), 2)
            exps = np.full(len(d), n)
            maps = glossy_prefilter.PrefilteredMaps(sky_pyramid)
            assert glossy_prefilter.worth_prefiltering(sky_pyramid, n, len(d))
            fast = glossy_prefilter.specular(maps, d, modes, exps) @ LUMA
            slow = glossy.specular(sky_pyramid, d, modes, exps) @ LUMA
            assert np.median(np.abs(fast / slow - 1.0)) < 0.005, rho
            assert maps.prefilter_ms > 0.0

    @pytest.mark.parametrize("roughness", [0.2, 0.5])
    def test_no_further_from_the_integral_than_the_per_pixel_kernel(self, roughness):
        hdr = synthetic_sky(512)
        pyr = glossy.mip_pyramid(hdr)
        n = glossy.phong_exponent(roughness)
        lum = hdr @ LUMA.astype(np.float32)
        i, j = np.unravel_index(int(np.argmax(lum)), lum.shape)
        sun = equirect.pixel_directions(*lum.shape)[i, j]
        near = sun + 0.05 * np.random.default_rng(1).normal(size=(32, 3))
        for dirs in (_random_directions(400), near / np.linalg.norm(near, axis=1)[:, None]):
            ref = glossy.glossy_brute_force(hdr, dirs, roughness) @ LUMA
            per_pixel = glossy.glossy(pyr, dirs, roughness) @ LUMA
            mapped = glossy.lookup(glossy_prefilter.prefiltered_map(pyr, n), dirs) @ LUMA
            for stat in (np.median, np.sum):
                old = stat(np.abs(per_pixel - ref) / ref)
                assert stat(np.abs(mapped - ref) / ref) <= 1.02 * old, (roughness, stat)

    def test_mixed_modes_and_the_per_pixel_fallback(self, sky_pyramid):
        d = _random_directions(3000, seed=1)
        modes = np.resize(np.array([0, 1, 2, 2]), len(d))
        # roughness 0.3 on many pixels (prefiltered), 0.01 on few (per pixel: its map is
        # the full-size one)
        exps = np.resize(np.array([0.0, 0.0, glossy.phong_exponent(0.3), 19998.0]), len(d))
        assert not glossy_prefilter.worth_prefiltering(sky_pyramid, 19998.0, 750)
        maps = glossy_prefilter.PrefilteredMaps(sky_pyramid)
        fast = glossy_prefilter.specular(maps, d, modes, exps)
        slow = glossy.specular(sky_pyramid, d, modes, exps)
        assert np.all(fast[modes == 0] == 0.0)
        for rows in (modes == 1, exps == 19998.0):  # mirror and per-pixel rows: the kernel's
            np.testing.assert_array_equal(fast[rows], slow[rows])
        rows = exps == glossy.phong_exponent(0.3)
        np.testing.assert_allclose(fast[rows], slow[rows], rtol=0.05)


def _scene(material: Material) -> VirtualScene:
    demo = ibl_render.demo_scene()
    import dataclasses

    return VirtualScene(tuple(dataclasses.replace(o, material=material) for o in demo.objects))


class TestRenderAgainstThePerPixelPath:
    @pytest.mark.parametrize("roughness", [0.1, 0.2, 0.3])
    def test_psnr_at_least_40_db(self, monkeypatch, roughness):
        hdr = synthetic_sky(1024)
        light_args = (hdr, diffuse_map_brute_force(hdr, (32, 16)))
        renderer = ibl_render.IblRenderer(_scene(Material((0.9, 0.9, 0.9), roughness, 1.0)))
        view = renderer.prepare_view(
            ibl_render.view_camera((320, 180), 75.0), ibl_render.look_along([0.0, 0.0, 1.0])
        )
        # a 320x180 view has too few pixels for the maps to pay: both ways forced
        monkeypatch.setattr(glossy_prefilter, "worth_prefiltering", lambda *a: True)
        light = ibl_render.frame_light(*light_args)
        fast = renderer.render(view, light)
        assert light.prefilter_ms > 0.0
        monkeypatch.setattr(glossy_prefilter, "worth_prefiltering", lambda *a: False)
        slow = renderer.render(view, ibl_render.frame_light(*light_args))
        assert _psnr(fast.rgb, slow.rgb) >= 40.0
        # the larger differences sit about the sun's reflection (the sky's sun is 10 000
        # times its median radiance), where the per-pixel pattern ripples as its rings
        # cross the sun (against the integral: the test above): under 2 % of the objects
        diff = np.abs(fast.rgb.astype(int) - slow.rgb).max(axis=-1)[fast.mask]
        assert np.mean(diff > 4) < 0.02, (np.mean(diff > 4), diff.max())
        np.testing.assert_array_equal(fast.rgb[~fast.mask], slow.rgb[~slow.mask])

    def test_diffuse_scene_makes_no_pyramid(self):
        hdr = synthetic_sky(256)
        renderer = ibl_render.IblRenderer(_scene(Material((0.8, 0.8, 0.8))))
        view = renderer.prepare_view(
            ibl_render.view_camera((160, 90), 75.0), ibl_render.look_along([0.0, 0.0, 1.0])
        )
        light = ibl_render.frame_light(hdr, diffuse_map_brute_force(hdr, (32, 16)), None, 1.0)
        renderer.render(view, light)
        assert light._pyramid is None and light.pyramid_ms == 0.0

    def test_mirror_scene_reads_level_0_without_a_pyramid(self):
        hdr = synthetic_sky(256)
        hdr[3, 4] = np.nan  # taken as 0, as the pyramid's level 0 takes it
        renderer = ibl_render.IblRenderer(_scene(Material((0.9, 0.9, 0.9), mirror=True)))
        view = renderer.prepare_view(
            ibl_render.view_camera((160, 90), 75.0), ibl_render.look_along([0.0, 0.0, 1.0])
        )
        light = ibl_render.frame_light(hdr, diffuse_map_brute_force(synthetic_sky(256), (32, 16)))
        out = renderer.render(view, light)
        assert light._pyramid is None
        pyr = glossy.mip_pyramid(hdr)
        want = glossy.specular(pyr, view.mirror_dirs, view.modes, view.exponents)
        np.testing.assert_array_equal(
            out.radiance.reshape(-1, 3)[view.pixels], (view.specular_rgb * want).astype(np.float32)
        )


class TestBackground:
    def test_bilinear_wrapped_and_clamped_as_the_numpy_oracle(self):
        rng = np.random.default_rng(2)
        ldr = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
        renderer = ibl_render.IblRenderer(VirtualScene())
        # looking up, across the seam (-z): rows clamp at the pole, columns wrap
        view = renderer.prepare_view(
            ibl_render.view_camera((200, 150), 120.0),
            ibl_render.look_along(np.array([0.0, 0.8, -0.6])),
        )
        light = ibl_render.frame_light(ldr.astype(np.float32), np.zeros((16, 32, 3)), ldr)
        got = renderer.render(view, light).rgb.astype(np.float64)
        x = view.uv[..., 0].astype(np.float64) * 128 - 0.5
        y = np.clip(view.uv[..., 1].astype(np.float64) * 64 - 0.5, 0, 63)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        y1 = np.minimum(y0 + 1, 63)
        img = ldr.astype(np.float64)

        def at(r, c):
            return img[r, c % 128]

        want = (1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) + fy * (
            (1 - fx) * at(y1, x0) + fx * at(y1, x0 + 1)
        )
        assert np.abs(got - want).max() <= 1.5  # OpenCV's 1/32-pixel weights, rounding
        assert (view.uv[..., 0] < 0.02).any() and (view.uv[..., 0] > 0.98).any()  # the seam


class TestMapPathKernels:
    @pytest.mark.parametrize("start, full, boost", [(235, 252, 5.0), (240, 240, 3.0)])
    def test_boost_kernel_bit_for_bit_the_numpy_oracle(self, start, full, boost):
        from arlight.pipeline import inverse_tone

        rng = np.random.default_rng(4)
        ldr = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
        ldr[:8] = rng.integers(230, 256, (8, 128, 3), dtype=np.uint8)  # clipped cores
        got = inverse_tone.boost_saturated(ldr, boost, start, full)
        want = inverse_tone.boost_saturated_numpy(ldr, boost, start, full)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, want)
        # a strided view (every other column) gives the same as its copy
        np.testing.assert_array_equal(
            inverse_tone.boost_saturated(ldr[:, ::2]),
            inverse_tone.boost_saturated_numpy(ldr[:, ::2]),
        )

    def test_whole_block_downsample_as_area_resampling(self):
        rng = np.random.default_rng(5)
        image = (rng.random((256, 512, 3)) ** 3 * 10).astype(np.float32)
        omega = equirect.row_solid_angles(256, 512).astype(np.float32)
        for w, h in ((128, 64), (32, 16), (512, 256)):
            got = equirect.downsample(image, w, h)
            # the oracle: OpenCV's INTER_AREA of the solid-angle-weighted map / of the weights
            num = cv2.resize(image * omega[:, None, None], (w, h), interpolation=cv2.INTER_AREA)
            den = cv2.resize(
                np.ascontiguousarray(np.broadcast_to(omega[:, None], (256, 512))),
                (w, h),
                interpolation=cv2.INTER_AREA,
            )
            np.testing.assert_allclose(got, num / den[..., None], rtol=2e-5)
        image[3, 4, 1] = np.nan  # NaN still propagates (no fast-math on NaN)
        assert np.isnan(equirect.downsample(image, 128, 64)).sum() == 1


class TestPyramidBuffer:
    def test_built_in_the_callers_buffer_frame_after_frame(self):
        buffer = np.empty((glossy.packed_rows(64), 3), np.float32)
        for seed in (1, 2):
            hdr = np.random.default_rng(seed).random((64, 128, 3)).astype(np.float32)
            pyr = glossy.mip_pyramid(hdr, buffer)
            assert np.shares_memory(pyr.data, buffer)
            fresh = glossy.mip_pyramid(hdr)
            np.testing.assert_array_equal(pyr.data, fresh.data)
        small = np.empty((10, 3), np.float32)  # too small: a new array instead
        assert not np.shares_memory(glossy.mip_pyramid(hdr, small).data, small)


class TestCliWriter:
    def test_renders_written_by_the_writer_thread_in_order(self, tmp_path, capsys):
        from arlight.cli import main

        out = tmp_path / "r"
        argv = ["ibl", "--max-frames", "3", "--out", str(tmp_path / "o.jsonl")]
        assert main([*argv, "--render", str(out), "--render-size", "96x54"]) == 0
        images = [cv2.imread(str(out / f"{i:06d}.png")) for i in range(3)]
        assert all(im is not None and im.shape == (54, 96, 3) for im in images)
        assert not np.array_equal(images[0], images[1])  # the sky turns between frames

    def test_a_failed_write_exits_2_naming_render(self, tmp_path, capsys):
        from arlight.cli import EXIT_BAD_INPUT, main

        out = tmp_path / "r"
        (out / "000001.png").mkdir(parents=True)  # a folder where frame 1's PNG goes
        argv = ["ibl", "--max-frames", "3", "--out", str(tmp_path / "o.jsonl")]
        code = main([*argv, "--render", str(out), "--render-size", "96x54"])
        err = capsys.readouterr().err
        assert code == EXIT_BAD_INPUT
        assert "--render" in err and "cannot write" in err and "000001.png" in err
        assert "Traceback" not in err
