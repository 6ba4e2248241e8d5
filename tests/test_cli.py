"""The `arlight` command on bad input: exit code 2, a message naming the flag, no traceback.

Each case runs the real CLI entry point (`arlight.cli.main`) in this process, with what a
user would type; argparse's own errors exit through SystemExit(2), ours return 2.
"""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import open3d.core as o3c
import pytest
from conftest import run_cli

from arlight.cli import EXIT_BAD_INPUT


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A decodable colour + depth pair, random bytes named .png, a non-image."""
    d = tmp_path_factory.mktemp("cli")
    cv2.imwrite(str(d / "shot_color.png"), np.full((12, 16, 3), 128, np.uint8))
    cv2.imwrite(str(d / "shot_depth.png"), np.full((12, 16), 5000, np.uint16))
    cv2.imwrite(str(d / "blank_depth.png"), np.zeros((12, 16), np.uint16))
    rng = np.random.default_rng(0)
    (d / "noise_color.png").write_bytes(rng.bytes(300))
    (d / "noise_depth.png").write_bytes(rng.bytes(300))
    return d


# (argv, text the message must contain); {d} is the fixture folder
BAD_INPUT = [
    (["bench", "--frames", "0"], "--frames"),
    (["bench", "--warmup", "-1"], "--warmup"),
    (["bench", "--frames", "many"], "--frames"),
    (["bench", "--sweep", "bogus=1,2"], "--sweep"),
    (["bench", "--sweep", "size=64x48", "/no/such/folder"], "--sweep size"),
    (["bench", "/no/such/folder"], "DATA"),
    (["bench", "--presets", "quick"], "--presets"),
    (["estimate", "--max-frames", "0"], "--max-frames"),
    (["estimate", "--set", "rt_directions=x"], "--set rt_directions"),
    (["estimate", "--set", "rt_directions=2"], "--set rt_directions"),
    (["estimate", "--set", "no_such_key=1"], "--set"),
    (["estimate", "--set", "rt_visibility_ramp=sideways"], "--set rt_visibility_ramp"),
    (["estimate", "--set", "sh_bands=0"], "--set sh_bands"),
    (["estimate", "--set", "change_reset_deg=200"], "change_reset_deg must be in (0, 180]"),
    (["estimate", "/no/such/folder"], "no such file"),
    (["estimate", "{d}/noise_color.png", "--depth", "{d}/noise_depth.png"], "not an image"),
    (
        [
            "estimate",
            "{d}/shot_color.png",
            "--depth",
            "{d}/noise_depth.png",
            "--depth-encoding",
            "tum",
        ],
        "not an image",
    ),
    (["estimate", "{d}/shot_color.png", "--depth", "{d}/shot_depth.png"], "--depth-encoding"),
    (
        [
            "estimate",
            "{d}/shot_color.png",
            "--depth",
            "{d}/shot_depth.png",
            "--depth-encoding",
            "mm",
            "--poses",
            "groundtruth",
        ],
        "--poses",
    ),
    (["--open3d-threads", "0", "estimate"], "--open3d-threads"),
    (["stream", "synthetic", "--size", "100000x100000"], "--size"),
    (["stream", "synthetic", "--size", "4x4"], "--size"),
    (["stream", "synthetic", "--max-frames", "0"], "--max-frames"),
    (["stream", "synthetic", "--jpeg-quality", "0"], "--jpeg-quality"),
    (["stream", "synthetic", "--server", "localhost:5555"], "--server"),
    (["record", "synthetic", "--out", "{d}/stream.txt"], "--out"),
    (["serve", "--bind", "5555"], "--bind"),
    (["serve", "--workers", "0"], "--workers"),
    (
        ["display", "--server", "tcp://127.0.0.1:1", "--session", "x", "--video", "{d}/v.avi"],
        "--video",
    ),
    (["demo", "--frames", "0"], "--frames"),
]


@pytest.mark.parametrize(
    "argv, names", BAD_INPUT, ids=lambda v: " ".join(v) if isinstance(v, list) else None
)
def test_bad_input_names_the_flag(argv, names, files, capsys):
    code, text = run_cli([a.format(d=files) for a in argv], capsys)
    assert "Traceback" not in text, text
    assert code == EXIT_BAD_INPUT, (code, text)
    assert names in text, text


@pytest.mark.skipif(o3c.cuda.is_available(), reason="CUDA is available here")
def test_cuda_device_without_cuda_is_a_usage_error(capsys):
    code, text = run_cli(["estimate", "--device", "CUDA:0", "--max-frames", "1"], capsys)
    assert code == EXIT_BAD_INPUT and "Traceback" not in text
    assert "--device CPU:0" in text, text


@pytest.mark.skipif(o3c.cuda.is_available(), reason="CUDA is available here")
def test_a_session_asking_for_cuda_is_refused_at_hello():
    """The server checks the device when the session is set up, not on every frame."""
    from types import SimpleNamespace

    from arlight.server.session import SessionSetupError, pipeline_config

    with pytest.raises(SessionSetupError) as caught:
        pipeline_config(SimpleNamespace(preset="fast", overrides={"device": "CUDA:0"}))
    assert caught.value.field == "overrides" and "--set device=CPU:0" in str(caught.value)


def test_tiny_demo_runs_and_reports_what_it_could_not_measure(tmp_path, capsys):
    """16x12 frames give no estimate: the summary says '-' instead of failing to format."""
    code, text = run_cli(
        ["demo", "--size", "16x12", "--frames", "2", "--out", str(tmp_path / "out")], capsys
    )
    assert "Traceback" not in text, text
    assert code == 0, text
    assert "2/2 results" in text and "error median - deg" in text, text


def test_no_traceback_as_a_process():
    """The installed entry point as a user runs it (a fresh interpreter, real stderr)."""
    run = subprocess.run(
        [sys.executable, "-m", "arlight.cli", "bench", "--frames", "0"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == EXIT_BAD_INPUT
    assert "Traceback" not in run.stderr and "--frames" in run.stderr, run.stderr


def test_estimate_on_the_built_in_scene_compares_in_the_camera_frame(capsys):
    """Tracking's world is the first camera, the scene's is its own: compared in the camera
    frame both share, the error is the estimator's, not the frames' (80 deg)."""
    code, text = run_cli(
        ["--open3d-threads", "1", "estimate", "--preset", "fast", "--max-frames", "3"], capsys
    )
    assert code == 0, text
    median = float(text.split("median angular error of the dominant light: ")[1].split()[0])
    # 80 when the frames differ; the estimator itself is 15-35 deg off on this scene's first
    # frames (its sky below the horizon is not a ground's uniform glow: docs/results/accuracy.md)
    assert median < 45.0, text
    # `fast` keeps a compact source there (decision 0062): the scene's sun, in the same frame
    sun = text.split("a compact source on ")[1]
    assert float(sun.split(" median ")[1].split()[0]) < 15.0, text


def test_the_built_in_scene_s_truth_names_its_sun():
    """scene_truth's sun_camera is the scene's sun turned into each frame's camera frame, 14
    degrees below the first moment of the light above the horizon on the first frame."""
    from arlight.evaluation import angular_error_deg, scene_truth
    from arlight.sources.synthetic import make_sequence

    scene = make_sequence(num_frames=3, width=64, height=48)
    for frame, sun, truth in zip(
        scene.frames, scene.sun_direction_world, scene_truth(scene), strict=True
    ):
        np.testing.assert_allclose(np.asarray(frame.pose)[:3, :3] @ truth.sun_camera, sun)
    first = scene_truth(scene)[0]
    assert 10.0 < angular_error_deg(first.sun_camera, first.dominant_upper_camera) < 20.0


def test_estimate_tracks_the_first_frames_of_the_built_in_scene(tmp_path, capsys):
    """`arlight estimate --max-frames 4` on the built-in scene takes the first 4 frames of its
    orbit, steps that tracking follows: each tracked camera is within 3 cm of the truth (a
    4-frame orbit, 25 degrees a step, was tracked 0.7-2.6 m off, every frame said "ok")."""
    from arlight.sources.synthetic import CLI_FRAMES, make_sequence

    out = tmp_path / "built_in.jsonl"
    code, text = run_cli(
        ["estimate", "--preset", "fast", "--max-frames", "4", "--out", str(out)], capsys
    )
    assert code == 0, text
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 4
    truth = [np.asarray(f.pose) for f in make_sequence(num_frames=CLI_FRAMES).frames]
    first_from_world = np.linalg.inv(truth[0])  # tracking's world is the first camera
    off_m = [
        float(np.linalg.norm((first_from_world @ pose)[:3, 3] - np.array(r["pose"])[:3, 3]))
        for r, pose in zip(records, truth, strict=False)
    ]
    assert max(off_m) < 0.03, off_m


class TestFrontDoor:
    """What `arlight --help`, `stream --help` and `estimate` tell a new user (issue 38)."""

    def test_help_describes_what_exists(self, capsys):
        code, text = run_cli(["--help"], capsys)
        assert code == 0
        assert "not there yet" not in text
        for command in ("estimate", "serve", "stream", "ibl", "bench", "batch", "synth"):
            assert command in text, command
        assert "--scene" in text and "live cameras" in text

    def test_composite_help_says_what_the_server_sends(self, capsys):
        """The server's composite is the colour image with the virtual objects rendered in
        (server/session.py, Session.composite), not the light drawn in."""
        code, text = run_cli(["stream", "--help"], capsys)
        assert code == 0
        flat = " ".join(text.split())
        assert "light drawn in" not in flat
        assert "the --scene objects rendered in" in flat
        assert "without --scene, the input colour image unchanged" in flat

    def test_settings_over_the_servers_budget_are_refused_before_any_frame(self, capsys):
        code, text = run_cli(
            ["estimate", "--max-frames", "1", "--set", "rt_directions=100000000"], capsys
        )
        assert code == EXIT_BAD_INPUT and "Traceback" not in text
        assert "--set rt_directions=100000000" in text, text
        assert "per-frame deadline of 60 s" in text and "--frame-deadline" in text, text
        assert "[   1/1]" not in text  # refused before the pipeline ran

    def test_the_deadline_is_the_users_to_set(self, capsys):
        """--frame-deadline 0.001 prices even the defaults out: the error names what costs
        most (here the image size) and the limit given."""
        code, text = run_cli(["estimate", "--max-frames", "1", "--frame-deadline", "0.001"], capsys)
        assert code == EXIT_BAD_INPUT and "Traceback" not in text
        assert "image size 640x480" in text and "deadline of 0.001 s" in text, text

    def test_a_frame_without_depth_says_so(self, files, tmp_path, capsys):
        out = tmp_path / "blank.jsonl"
        code, text = run_cli(
            [
                "estimate",
                f"{files}/shot_color.png",
                "--depth",
                f"{files}/blank_depth.png",
                "--depth-encoding",
                "mm",
                "--out",
                str(out),
            ],
            capsys,
        )
        assert code == 0, text
        assert "[1/1] no usable depth" in text, text
        assert "1 of 1 frames without usable depth" in text, text
        record = json.loads(out.read_text())
        assert record["confidence"]["value"] == 0.0  # the record itself is unchanged

    def test_a_low_confidence_prints_its_reason(self, files, tmp_path, capsys):
        """A flat wall of 16x12 pixels constrains no direction: the reason the pipeline gives
        (Confidence.reason, also in the record) is on the terminal."""
        out = tmp_path / "wall.jsonl"
        code, text = run_cli(
            [
                "estimate",
                f"{files}/shot_color.png",
                "--depth",
                f"{files}/shot_depth.png",
                "--depth-encoding",
                "mm",
                "--out",
                str(out),
            ],
            capsys,
        )
        assert code == 0, text
        confidence = json.loads(out.read_text())["confidence"]
        assert confidence["value"] < 0.3 and confidence["reason"], confidence
        assert f"[1/1] low confidence {confidence['value']:.2f}" in text, text
        assert confidence["reason"] in text, text
