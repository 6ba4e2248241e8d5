"""HDR environment maps from SH light (pipeline/environment_map.py) and `arlight estimate
--env-exr / --cubemap / --export`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from arlight.cli import EXIT_BAD_INPUT, main
from arlight.evaluation import angular_error_deg
from arlight.pipeline import equirect, sh
from arlight.pipeline.environment_map import (
    CUBE_FACES,
    cube_face_directions,
    cubemap_from_sh,
    equirect_from_sh,
)
from arlight.sources.exr import read_exr

LIGHT = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])


def _light_rgb() -> np.ndarray:
    mono = sh.directional_light(LIGHT, 3.0, 4)
    return np.stack([mono, 0.5 * mono, 0.25 * mono])


def test_equirect_is_the_sh_at_each_pixel_direction_clamped():
    image = equirect_from_sh(_light_rgb(), 64)
    assert image.shape == (32, 64, 3) and image.dtype == np.float32
    dirs = equirect.pixel_directions(32, 64)
    expected = np.maximum(sh.evaluate(_light_rgb(), dirs.reshape(-1, 3)).T, 0.0)
    np.testing.assert_allclose(image.reshape(-1, 3), expected, rtol=1e-5, atol=1e-6)
    assert image.min() >= 0.0  # the band-limited light's negative lobes are cut
    brightest = dirs.reshape(-1, 3)[np.argmax(image[..., 0])]
    assert angular_error_deg(brightest, LIGHT) < 6.0  # within a pixel or so


def test_cube_faces_follow_the_opengl_table():
    """Face centres are the axes; the top-left texel of +X looks along (1, 1, 1) and that of
    +Y along (-1, 1, -1) (OpenGL 4.6 table 8.19, t from the top row)."""
    axes = {
        "px": (1, 0, 0),
        "nx": (-1, 0, 0),
        "py": (0, 1, 0),
        "ny": (0, -1, 0),
        "pz": (0, 0, 1),
        "nz": (0, 0, -1),
    }
    for face in CUBE_FACES:
        d = cube_face_directions(face, 3)
        np.testing.assert_allclose(d[1, 1], axes[face], atol=1e-12)
    corner = cube_face_directions("px", 1000)[0, 0]
    np.testing.assert_allclose(corner, np.ones(3) / math.sqrt(3), atol=2e-3)
    corner = cube_face_directions("py", 1000)[0, 0]
    np.testing.assert_allclose(corner, np.array([-1, 1, -1]) / math.sqrt(3), atol=2e-3)


def test_cubemap_of_a_light_along_plus_x_is_brightest_at_that_face_centre():
    faces = cubemap_from_sh(sh.directional_light(np.array([1.0, 0.0, 0.0]), 1.0, 4), 9)
    peak = max(faces, key=lambda f: faces[f].max())
    assert peak == "px"
    assert np.unravel_index(np.argmax(faces["px"][..., 0]), (9, 9)) == (4, 4)


def test_bad_sizes_and_shapes_are_refused():
    with pytest.raises(ValueError, match="even"):
        equirect_from_sh(_light_rgb(), 63)
    with pytest.raises(ValueError, match="shape"):
        equirect_from_sh(np.zeros((2, 16)), 64)


def test_estimate_writes_maps_faces_and_engine_layouts(tmp_path, capsys):
    out = tmp_path / "r.jsonl"
    code = main(
        [
            "estimate",
            "--max-frames",
            "2",
            "--out",
            str(out),
            "--env-exr",
            str(tmp_path / "env"),
            "--env-size",
            "32",
            "--cubemap",
            "--export",
            "arcore,webxr,gltf,unity,filament",
        ]
    )
    capsys.readouterr()
    assert code == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 2
    exports = records[0]["exports"]
    assert len(exports["arcore"]) == 27 and len(exports["webxr"]) == 27
    assert len(exports["unity"]) == 3 and "(" in exports["filament"]
    hdr = read_exr(tmp_path / "env" / "000001.exr")
    assert hdr.shape == (16, 32, 3) and np.isfinite(hdr).all() and hdr.max() > 0
    # the map is the record's own SH (world frame), to half-float precision
    sh_world = np.asarray(records[1]["sh"])
    expected = equirect_from_sh(sh_world, 32)
    np.testing.assert_allclose(hdr, expected, rtol=2e-3, atol=1e-4)
    for face in CUBE_FACES:
        assert read_exr(tmp_path / "env" / f"000000_{face}.exr").shape == (8, 8, 3)


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["--cubemap"], "--env-exr"),
        (["--export", "opengl"], "--export"),
        (["--env-exr", "x", "--env-size", "33"], "--env-size"),
    ],
)
def test_bad_environment_flags_exit_2_naming_the_flag(tmp_path, capsys, argv, flag):
    argv = [a if a != "x" else str(tmp_path / "x") for a in argv]
    try:
        code = main(["estimate", "--max-frames", "1", *argv])
    except SystemExit as exc:
        code = exc.code
    text = capsys.readouterr().err
    assert code in (2, EXIT_BAD_INPUT) and flag in text and "Traceback" not in text


def test_cubemap_of_an_equirect_map_puts_its_bright_patch_on_the_right_face():
    """A patch around +X in the equirectangular map (column u = 0.25: atan2(x, -z) = 90 deg)
    lands at the centre of the +X face, nowhere on -X."""
    from arlight.pipeline.environment_map import cubemap_from_equirect

    hdr = np.full((64, 128, 3), 0.1, np.float32)
    hdr[28:36, 28:36] = 5.0
    faces = cubemap_from_equirect(hdr, 16)
    assert faces["px"][8, 8, 0] > 4.0 and faces["nx"].max() < 0.2
    assert all(f.shape == (16, 16, 3) for f in faces.values())


def test_ibl_cubemap_writes_six_faces_per_frame(tmp_path, capsys):
    code = main(["ibl", "--max-frames", "1", "--exr", str(tmp_path / "hdr"), "--cubemap"])
    capsys.readouterr()
    assert code == 0
    hdr = read_exr(tmp_path / "hdr" / "000000.exr")
    for face in CUBE_FACES:
        assert read_exr(tmp_path / "hdr" / f"000000_{face}.exr").shape == (
            hdr.shape[0] // 2,
            hdr.shape[0] // 2,
            3,
        )
    try:
        code = main(["ibl", "--max-frames", "1", "--cubemap"])
    except SystemExit as exc:
        code = exc.code
    assert code in (2, EXIT_BAD_INPUT) and "--exr" in capsys.readouterr().err
