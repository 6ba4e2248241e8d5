"""The 360-degree lighting path: equirect mapping, inverse tone mapping, per-frame lighting,
panorama sources, `arlight ibl` and its OpenEXR output.

Data-driven cases read the HDR maps of ../shared/data/hdri and skip with a message when it
is absent; everything else builds its input here (the built-in sky, small written videos).
"""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DATA, needs_data

from arlight.cli import EXIT_BAD_INPUT, main
from arlight.pipeline import equirect, sh
from arlight.pipeline.color import LUMA, srgb_to_linear
from arlight.pipeline.ibl import (
    IblParams,
    angle_deg,
    diffuse_map_brute_force,
    diffuse_map_sh,
    lighting_from_hdr,
    lighting_from_ldr,
    radiance_sh,
)
from arlight.pipeline.inverse_tone import OPERATORS, expand, paper_expand
from arlight.sources.exr import read_exr, write_exr
from arlight.sources.panorama import PanoramaError, open_panorama
from arlight.sources.synthetic_panorama import ldr_frame, synthetic_sky

HDRI = DATA / "hdri"
HDR_FILES = sorted(HDRI.glob("*.hdr")) if HDRI.is_dir() else []
needs_hdri = needs_data(HDRI)


def r_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@pytest.fixture(scope="module")
def sky_ldr() -> np.ndarray:
    """The built-in sky (sun 35 degrees up, azimuth 60), 512x256, as a camera records it."""
    return ldr_frame(synthetic_sky(512), 0.18)


@pytest.fixture(scope="module")
def hdr_maps() -> dict[str, np.ndarray]:
    from arlight.sources.panorama import read_panorama_image

    return {f.name: read_panorama_image(f) for f in HDR_FILES}


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own usage errors
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> None:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert writer.isOpened(), "OpenCV cannot write mp4v here"
    for f in frames:
        writer.write(np.ascontiguousarray(f[..., ::-1]))
    writer.release()


class TestEquirect:
    def test_mapping_as_the_data_readme_states(self):
        # +z at the centre column, +x a quarter in, -z at the seam, +y on the top row
        dirs = np.array([[0, 0, 1], [1, 0, 0], [0, 0, -1], [-1, 0, 0], [0, 1, 0], [0, -1, 0.0]])
        u, v = equirect.uv_of(dirs)
        np.testing.assert_allclose(u[:4], [0.5, 0.25, 0.0, 0.75], atol=1e-12)
        np.testing.assert_allclose(v, [0.5, 0.5, 0.5, 0.5, 0.0, 1.0], atol=1e-12)
        rng = np.random.default_rng(1)
        d = rng.normal(size=(100, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        np.testing.assert_allclose(equirect.directions_of(*equirect.uv_of(d)), d, atol=1e-12)

    def test_solid_angles_and_area_correct_downsampling(self):
        assert equirect.pixel_solid_angles(64, 128).sum() == pytest.approx(4 * math.pi)
        rng = np.random.default_rng(2)
        image = rng.random((64, 128, 3)).astype(np.float32)
        for w, h in ((64, 32), (32, 16), (30, 15)):
            small = equirect.downsample(image, w, h)
            np.testing.assert_allclose(
                (small * equirect.pixel_solid_angles(h, w)[..., None]).sum((0, 1)),
                (image * equirect.pixel_solid_angles(64, 128)[..., None]).sum((0, 1)),
                rtol=1e-4,
            )

    def test_rotation_about_y_is_a_column_shift(self):
        image = synthetic_sky(256)
        turned = equirect.rotate_about_y(image, math.pi / 2)
        d = np.array([0.3, 0.4, -0.866])
        d /= np.linalg.norm(d)
        np.testing.assert_allclose(
            equirect.sample_bilinear(turned, r_y(math.pi / 2) @ d),
            equirect.sample_bilinear(image, d),
            rtol=1e-5,
        )


class TestInverseTone:
    def test_paper_equations_by_hand(self):
        # white: L_i = 1, L_s = 11.8; mid grey 0.5: L_s = 10 / 1024 + 1.8
        out = paper_expand(np.array([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [1.0, 0.0, 0.0]]))
        np.testing.assert_allclose(out[0], 11.8, rtol=1e-6)
        np.testing.assert_allclose(out[1], 0.5 * (10 * 0.5**10 + 1.8), rtol=1e-6)
        np.testing.assert_allclose(out[2], [10 * 0.3**10 + 1.8, 0, 0], rtol=1e-6)
        grey = np.full((2, 4, 3), 128, np.uint8)
        lin = srgb_to_linear(grey)
        np.testing.assert_allclose(expand(grey, "paper"), paper_expand(grey / 255.0), rtol=1e-6)
        np.testing.assert_allclose(expand(grey, "paper-linear"), paper_expand(lin), rtol=1e-6)

    def test_boost_keeps_unclipped_pixels_and_boosts_clipped_white(self):
        image = np.array(
            [[[10, 120, 200], [255, 255, 255], [255, 90, 30], [255, 255, 240]]], dtype=np.uint8
        )
        out = expand(image, "boost")
        lin = srgb_to_linear(image)
        np.testing.assert_allclose(out[0, 0], lin[0, 0])  # unclipped: exact decoding
        np.testing.assert_allclose(out[0, 1], 5.0)  # white core x5
        np.testing.assert_allclose(out[0, 2], lin[0, 2])  # one channel clipped: as decoded
        assert 1.0 < out[0, 3, 0] < 5.0  # nearly white: part of the boost (smooth weight)

    def test_unknown_operator(self):
        with pytest.raises(ValueError, match="unknown inverse tone-mapping operator"):
            expand(np.zeros((4, 8, 3), np.uint8), "magic")


class TestLighting:
    def test_uniform_light_gives_pi_irradiance_everywhere(self):
        hdr = np.ones((64, 128, 3), np.float32)
        result = lighting_from_hdr(hdr)
        np.testing.assert_allclose(result.sh[0], 2 * math.sqrt(math.pi), rtol=1e-5)
        # pixel-centre quadrature over rows: band 2's sin^2 / cos^2 terms off by ~2e-4
        np.testing.assert_allclose(result.sh[1:], 0, atol=1e-3)
        np.testing.assert_allclose(result.diffuse_map, math.pi, rtol=0.02)
        np.testing.assert_allclose(diffuse_map_sh(result.sh_rgb), math.pi, rtol=1e-3)

    def test_brute_force_and_sh_agree_on_a_smooth_light(self):
        d = equirect.pixel_directions(128, 256)
        hdr = (1.0 + 0.8 * d[..., 1:2] + 0.3 * d[..., 0:1] * d[..., 2:3]).astype(np.float32)
        hdr = np.repeat(hdr, 3, axis=2)  # band-limited (bands 0-2): SH is exact
        brute = diffuse_map_brute_force(hdr, (64, 32), (128, 64))
        fast = diffuse_map_sh(radiance_sh(equirect.downsample(hdr, 128, 64)), (64, 32))
        np.testing.assert_allclose(brute, fast, rtol=0.01)

    def test_hdr_input_with_nan_inf_and_negative_values(self):
        hdr = np.ones((32, 64, 3), np.float32)
        hdr[0, 0], hdr[1, 1], hdr[2, 2] = np.nan, np.inf, -5.0
        r = lighting_from_hdr(hdr)
        assert np.all(np.isfinite(r.sh_rgb)) and np.all(r.diffuse_map >= 0)

    @pytest.mark.parametrize("value", [0, 255])
    def test_black_and_saturated_frames_give_finite_results(self, value):
        ldr = np.full((128, 256, 3), value, np.uint8)
        for op in OPERATORS:
            r = lighting_from_ldr(ldr, IblParams(operator=op))
            for a in (r.sh, r.sh_rgb, r.dominant_direction, r.diffuse_map):
                assert np.all(np.isfinite(a)), op
            assert np.linalg.norm(r.dominant_direction) in (0.0, pytest.approx(1.0))
        if value == 0:
            assert not np.any(r.dominant_direction) and not np.any(r.diffuse_map)

    def test_dominant_direction_rotates_with_the_panorama(self, sky_ldr):
        w = sky_ldr.shape[1]
        base = lighting_from_ldr(sky_ldr).dominant_direction
        # towards the sun's azimuth (60 degrees; the elevation is pulled up by the sky)
        assert math.degrees(math.atan2(base[0], -base[2])) == pytest.approx(60.0, abs=2.0)
        assert base[1] > 0
        for shift in (w // 8, w // 4, 3 * w // 8 + 5, w // 2 + 37):
            angle = 2 * math.pi * shift / w
            turned = lighting_from_ldr(np.roll(sky_ldr, -shift, axis=1)).dominant_direction
            assert angle_deg(turned, r_y(angle) @ base) < 0.5, shift
            assert turned[1] == pytest.approx(base[1], abs=5e-3)  # elevation unchanged

    @needs_hdri
    def test_real_map_rotation(self, hdr_maps):
        hdr = (
            hdr_maps["forest_slope_1k.hdr"]
            if "forest_slope_1k.hdr" in hdr_maps
            else next(iter(hdr_maps.values()))
        )
        ldr = ldr_frame(hdr, 0.18)
        base = lighting_from_ldr(ldr).dominant_direction
        w = ldr.shape[1]
        for shift in (w // 8, w // 3):
            turned = lighting_from_ldr(np.roll(ldr, -shift, axis=1)).dominant_direction
            assert angle_deg(turned, r_y(2 * math.pi * shift / w) @ base) < 0.5

    @needs_hdri
    def test_diffuse_map_from_ldr_correlates_with_hdr_truth(self, hdr_maps):
        """Pearson r over the 32x16 map pixels (luminance) between the map from the LDR frame
        (key 0.18, default operator) and the map from the HDR original. Measured: 0.98-0.998
        on four of the six maps; the warehouse's small lamps (0.3) and the studio's lights
        (-0.5: 30-1300 times the clip) are beyond what a fixed boost restores. Bound: r >=
        0.95 on at least 4 maps, median >= 0.95, and better than the plain LDR map."""
        r_default, r_linear = [], []
        for hdr in hdr_maps.values():
            truth = lighting_from_hdr(hdr).diffuse_map @ LUMA
            ldr = ldr_frame(hdr, 0.18)
            for op, out in (("boost", r_default), ("linear", r_linear)):
                got = lighting_from_ldr(ldr, IblParams(operator=op)).diffuse_map @ LUMA
                out.append(np.corrcoef(truth.ravel(), got.ravel())[0, 1])
        assert sum(r >= 0.95 for r in r_default) >= min(4, len(r_default)), r_default
        assert np.median(r_default) >= 0.95
        assert np.median(r_default) > np.median(r_linear)


class TestSources:
    def test_non_2_to_1_image_names_the_file_and_size(self, tmp_path):
        path = tmp_path / "wide_pano.png"
        cv2.imwrite(str(path), np.zeros((200, 300, 3), np.uint8))
        with pytest.raises(PanoramaError, match=r"wide_pano\.png.*2:1.*300x200"):
            open_panorama(path)

    def test_image_sequence_sorted_with_timestamps(self, tmp_path, sky_ldr):
        for i in (10, 2, 1):
            cv2.imwrite(str(tmp_path / f"frame{i}.png"), np.full((8, 16, 3), i, np.uint8))
        with open_panorama(tmp_path, fps=4.0) as src:
            got = [(t, int(img[0, 0, 0])) for t, img in src]
        assert got == [(0.0, 1), (0.25, 2), (0.5, 10)]

    def test_video_on_a_decode_thread_in_order(self, tmp_path):
        frames = [np.full((64, 128, 3), 50 * i, np.uint8) for i in range(6)]
        write_video(tmp_path / "pano.mp4", frames, fps=10.0)
        with open_panorama(tmp_path / "pano.mp4") as src:
            got = list(src)
        assert [round(t, 3) for t, _ in got] == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
        # in order, every frame (the codec moves flat levels by a few units)
        np.testing.assert_allclose(
            [img.mean() for _, img in got], [50 * i for i in range(6)], atol=8
        )
        with open_panorama(tmp_path / "pano.mp4", fps=2.0, max_frames=3) as src:
            assert [t for t, _ in src] == [0.0, 0.5, 1.0]
        src = open_panorama(tmp_path / "pano.mp4", queue_frames=1)
        for _ in src:
            break  # stopping early stops the decoder
        src.close()
        assert not any(
            t.name.startswith("decode pano") and t.is_alive() for t in threading.enumerate()
        )

    def test_exr_round_trip_is_half_float(self, tmp_path):
        import OpenEXR

        rgb = (np.random.default_rng(3).random((16, 32, 3)) * 100).astype(np.float32)
        write_exr(tmp_path / "m.exr", rgb)
        with OpenEXR.File(str(tmp_path / "m.exr")) as f:
            pixels = f.channels()["RGB"].pixels
            assert pixels.dtype == np.float16 and pixels.shape == (16, 32, 3)
        np.testing.assert_allclose(read_exr(tmp_path / "m.exr"), rgb, rtol=1e-3)


class TestCli:
    def test_default_runs_on_the_built_in_sky(self, capsys):
        code, out, err = run_cli(["ibl", "--max-frames", "3"], capsys)
        assert code == 0, err
        lines = [json.loads(line) for line in out.splitlines()]
        assert [r["frame"] for r in lines] == [0, 1, 2]
        for r in lines:
            assert len(r["sh"]) == 16 and np.shape(r["sh_rgb"]) == (3, 16)
            assert np.linalg.norm(r["dominant_direction"]) == pytest.approx(1.0)
            assert np.isfinite(r["angular_error_deg"])
        assert "dominant direction against the HDR original" in err

    def test_video_with_exr_output(self, tmp_path, capsys, sky_ldr):
        frames = [np.roll(sky_ldr, -k * 64, axis=1) for k in range(4)]  # 45 degrees per frame
        write_video(tmp_path / "sky.mp4", frames, fps=5.0)
        out_file, exr_dir = tmp_path / "r.jsonl", tmp_path / "exr"
        code, _, err = run_cli(
            [
                "ibl",
                str(tmp_path / "sky.mp4"),
                "--out",
                str(out_file),
                "--exr",
                str(exr_dir),
                "--diffuse-size",
                "16x8",
            ],
            capsys,
        )
        assert code == 0, err
        lines = [json.loads(line) for line in out_file.read_text().splitlines()]
        assert [round(r["timestamp"], 3) for r in lines] == [0.0, 0.2, 0.4, 0.6]
        d = [np.array(r["dominant_direction"]) for r in lines]
        for k in range(1, 4):  # through a real codec, the light turns with the sky
            assert angle_deg(d[k], r_y(k * math.pi / 4) @ d[0]) < 3.0
        # the EXR of the last frame: half float, the panorama's size, its HDR values
        import OpenEXR

        names = sorted(p.name for p in exr_dir.iterdir())
        assert names == [f"{i:06d}.exr" for i in range(4)]
        with OpenEXR.File(str(exr_dir / "000003.exr")) as f:
            pixels = np.array(f.channels()["RGB"].pixels)
        assert pixels.dtype == np.float16 and pixels.shape == (256, 512, 3)
        cap = cv2.VideoCapture(str(tmp_path / "sky.mp4"))
        for _ in range(4):
            ok, bgr = cap.read()
        np.testing.assert_allclose(
            pixels.astype(np.float32),
            expand(np.ascontiguousarray(bgr[..., ::-1])),
            rtol=2e-3,
            atol=1e-4,
        )
        assert pixels.max() == pytest.approx(5.0, rel=1e-3)  # the boosted sun

    @pytest.mark.parametrize(
        "argv, text",
        [
            (["--diffuse-size", "30x16"], "--diffuse-size"),
            (["--diffuse-size", "1024x512"], "--diffuse-size"),
            (["--fps", "0"], "--fps"),
            (["--operator", "magic"], "--operator"),
        ],
    )
    def test_bad_flags(self, capsys, argv, text):
        code, _, err = run_cli(["ibl", *argv], capsys)
        assert code == EXIT_BAD_INPUT and text in err and "Traceback" not in err

    def test_bad_panoramas(self, tmp_path, capsys):
        cv2.imwrite(str(tmp_path / "square.jpg"), np.zeros((64, 64, 3), np.uint8))
        (tmp_path / "broken.mp4").write_bytes(b"not a video at all")
        for path, text in (
            (tmp_path / "square.jpg", "(2:1), got 64x64"),
            (tmp_path / "broken.mp4", "broken.mp4"),
            (tmp_path / "missing.png", "missing.png"),
        ):
            code, _, err = run_cli(["ibl", str(path)], capsys)
            assert code == EXIT_BAD_INPUT and text in err and "Traceback" not in err, err

    def test_non_2_to_1_video_and_unwritable_out(self, tmp_path, capsys):
        write_video(tmp_path / "tall.mp4", [np.zeros((96, 64, 3), np.uint8)] * 2)
        code, _, err = run_cli(["ibl", str(tmp_path / "tall.mp4")], capsys)
        assert code == EXIT_BAD_INPUT and "tall.mp4" in err and "got 64x96" in err, err
        code, _, err = run_cli(["ibl", "--out", str(tmp_path / "no" / "dir.jsonl")], capsys)
        assert code == EXIT_BAD_INPUT and "--out" in err and "Traceback" not in err, err

    def test_exr_folder_that_cannot_be_made(self, tmp_path, capsys):
        (tmp_path / "file").write_text("x")
        code, _, err = run_cli(["ibl", "--exr", str(tmp_path / "file" / "sub")], capsys)
        assert code == EXIT_BAD_INPUT and "--exr" in err


def test_operators_listed_in_help(capsys):
    code, out, _ = run_cli(["ibl", "--help"], capsys)
    assert code == 0 and all(name in out for name in OPERATORS)


def test_sh_convention_of_the_path():
    """A small bright patch at a known direction gives band 1 as the project's basis says:
    c_1,-1 : c_1,0 : c_1,1 = y : z : x."""
    d = np.array([0.48, 0.6, -0.64])
    hdr = np.full((64, 128, 3), 1e-3, np.float32)
    u, v = equirect.uv_of(d)
    hdr[int(v * 64), int(u * 128)] = 1000.0
    c = lighting_from_hdr(hdr).sh
    assert angle_deg(np.array([c[3], c[1], c[2]]), d) < 3.0
    assert angle_deg(sh.dominant_direction(c), d) < 3.0
