"""`arlight stream --probe SIZE [--probe-at X,Y,Z] [--probe-mips] [--probe-out DIR
[--probe-layout ENGINE]]` (issue 33, item 3) over a real server on loopback: the Results'
probes written as OpenEXR cube faces (a red wall on the world's +x lands in the +X face), the
--out lines say what came and where it went, bad flags exit 2 naming the flag, and the
server's refusal is one line naming the flag."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from conftest import SMALL, run_cli

from arlight.cli.client_options import probe_request
from arlight.cli.common import BadInput
from arlight.core.camera import PinholeCamera
from arlight.protocols import PROTOCOL_VERSION, Frame, Hello, SessionConfig, encode
from arlight.protocols.probe import ProbeRequest
from arlight.sources.exr import read_exr
from arlight.sources.source import calibration_of

NOWHERE = ["--server", "tcp://127.0.0.1:9", "--reconnect-timeout", "1"]
FACES = ("px", "nx", "py", "ny", "pz", "nz")

# camera-to-world: a quarter turn about y, so the camera's +z (ahead) is the world's +x
LOOK_ALONG_X = np.array(
    [[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def _red_wall_recording(path, frames: int = 2) -> None:
    """FILE.mcap of `frames` 64x48 frames of a red wall 1.5 m ahead of a camera posed to
    look along world +x (the frames carry the pose: no tracking), lossless, preset fast."""
    from arlight.client.recording import Recorder

    config = SessionConfig(
        "wall",
        calibration=calibration_of(PinholeCamera.kinect_v1(64, 48)),
        depth_scale=5000.0,
        preset="fast",
        overrides=dict(SMALL),
        mode="lossless",
    )
    color = np.zeros((48, 64, 3), np.uint8)
    color[...] = (200, 30, 30)
    depth = np.full((48, 64), 7500, np.uint16)  # 1.5 m
    with Recorder(path, source="wall", depth_scale=5000.0) as rec:
        rec.write_hello(encode(Hello(PROTOCOL_VERSION, config)), 1_000_000_000)
        for seq in range(frames):
            frame = Frame(seq, 1.0 + seq, color, depth, LOOK_ALONG_X, None, "raw", "raw")
            rec.write_frame(encode(frame), int((1.0 + seq) * 1e9))


def _red_share(folder, stem: str, level: int = 0) -> dict[str, float]:
    """Per face, the share of texels that are red (R over twice G)."""
    share = {}
    for face in FACES:
        image = read_exr(folder / f"{stem}_{face}_m{level}.exr")
        share[face] = float(np.mean(image[..., 0] > 2.0 * image[..., 1]))
    return share


@pytest.mark.parametrize("layout, ahead", [("world", "px"), ("threejs", "nz")])
def test_a_red_wall_on_plus_x_lands_in_the_written_faces(
    make_server, tmp_path, capsys, layout, ahead
):
    """world: the session's axes, the wall on +x is in px. threejs: the camera frame with
    OpenGL's axes, where ahead is -z (three.js mirrors x only): nz."""
    server = make_server(heartbeat_interval_s=20.0)  # the first frame compiles kernels
    recording, probes, out = tmp_path / "wall.mcap", tmp_path / "probes", tmp_path / "r.jsonl"
    _red_wall_recording(recording)
    argv = ["stream", str(recording), "--server", server.connect_address, "--rate", "max"]
    argv += ["--probe", "32", "--probe-at", "0.75,0,0", "--probe-mips"]
    argv += ["--probe-out", str(probes), "--probe-layout", layout, "--out", str(out)]
    code, text = run_cli(argv, capsys)
    assert code == 0, text
    assert f"wrote 2 reflection probes to {probes}/" in text, text
    assert "probe 32 texels at (0.75, 0, 0) with mips" in text, text
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert [line["frame"] for line in lines] == [0, 1]
    for line in lines:
        probe = line["probe"]
        assert (
            probe["size"] == 32
            and probe["levels"] == 4
            and probe["point_world"]
            == [
                0.75,
                0.0,
                0.0,
            ]
        )
        assert probe["roughness"] == pytest.approx([0.0, 1 / 3, 2 / 3, 1.0])
        stem = f"{line['frame']:06d}"
        assert probe["files"] == {
            "json": str(probes / f"{stem}.json"),
            "faces": str(probes / f"{stem}_<face>_m<level>.exr"),
            "layout": layout,
        }
        info = json.loads((probes / f"{stem}.json").read_text())
        assert info["layout"] == layout and [lv["size"] for lv in info["levels"]] == [
            32,
            16,
            8,
            4,
        ]
        assert info["diagnostics"]["hit_fraction"] > 0.05
    assert len(out.read_text()) < 20_000  # the texels (4 levels: 32 KB as RGB9E5) stay out
    share = _red_share(probes, "000001")
    assert share[ahead] > 0.5, share
    assert max(v for face, v in share.items() if face != ahead) < 0.25, share
    opposite = {"px": "nx", "nz": "pz"}[ahead]
    assert share[opposite] == 0.0, share
    assert len(list(probes.glob("000001_*_m3.exr"))) == 6  # every level, every face


def test_a_scene_places_the_probe_at_its_objects_centre(make_server, tmp_path, capsys):
    """No --probe-at: the Hello's point is nil and the server puts the probe at the centre
    of the --scene objects (a small sphere at world (0.75, 0.05, 0), between the camera and
    the red wall), which sees the wall in its +X face."""
    server = make_server(heartbeat_interval_s=20.0)
    recording, probes, out = tmp_path / "wall.mcap", tmp_path / "probes", tmp_path / "r.jsonl"
    _red_wall_recording(recording)
    scene = tmp_path / "scene.json"
    ball = {
        "name": "ball",
        "primitive": {"shape": "sphere", "radius_m": 0.05},
        "world_from_object": [[1, 0, 0, 0.75], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    }
    scene.write_text(json.dumps({"objects": [ball]}))
    argv = ["stream", str(recording), "--server", server.connect_address, "--rate", "max"]
    argv += ["--scene", str(scene), "--scene-frame", "world", "--probe", "32"]
    code, text = run_cli(argv + ["--probe-out", str(probes), "--out", str(out)], capsys)
    assert code == 0, text
    last = [json.loads(x) for x in out.read_text().splitlines()][-1]
    # the sphere stands on its object origin (+y up in its frame): centre 0.05 along world y
    assert last["probe"]["point_world"] == pytest.approx([0.75, 0.05, 0.0], abs=1e-6)
    share = _red_share(probes, f"{last['frame']:06d}")
    assert share["px"] > 0.5 and share["nx"] == 0.0, share


def test_without_probe_out_the_lines_still_say_a_probe_came(make_server, tmp_path, capsys):
    server = make_server(heartbeat_interval_s=20.0)
    recording, out = tmp_path / "wall.mcap", tmp_path / "r.jsonl"
    _red_wall_recording(recording, frames=1)
    argv = ["stream", str(recording), "--server", server.connect_address, "--rate", "max"]
    code, text = run_cli(
        argv + ["--probe", "32", "--probe-at", "0.5,0,0", "--out", str(out)], capsys
    )
    assert code == 0, text
    (line,) = [json.loads(x) for x in out.read_text().splitlines()]
    assert line["probe"]["size"] == 32 and line["probe"]["levels"] == 1
    assert line["probe"]["files"] is None
    # and a session that did not ask has no probe key
    code, text = run_cli(argv + ["--out", str(out)], capsys)
    assert code == 0, text
    assert "probe" not in json.loads(out.read_text().splitlines()[0])


@pytest.mark.parametrize(
    "flags, names",
    [
        (["--probe", "48"], "--probe"),
        (["--probe", "512"], "--probe"),
        (["--probe", "16"], "--probe"),
        (["--probe", "big"], "--probe"),
        (["--probe", "64", "--probe-at", "1,2"], "--probe-at"),
        (["--probe", "64", "--probe-at", "0,nan,1"], "--probe-at"),
        (["--probe", "64", "--probe-at", "0,0,1e5"], "--probe-at"),
        (["--probe-at", "0,0,1"], "--probe"),
        (["--probe-mips"], "--probe"),
        (["--probe-out", "{d}/p"], "--probe"),
        (["--probe", "64", "--probe-at", "0,0,1", "--probe-layout", "threejs"], "--probe-out"),
        (["--probe", "64", "--probe-at", "0,0,1", "--probe-layout", "unity"], "--probe-layout"),
        (["--probe", "64"], "--probe-at"),  # no point and no scene: the message names both
    ],
)
def test_bad_probe_flags_exit_2_naming_the_flag(flags, names, tmp_path, capsys):
    argv = ["stream", "synthetic", "--max-frames", "1", *NOWHERE]
    code, text = run_cli(argv + [f.format(d=tmp_path) for f in flags], capsys)
    assert code == 2 and "Traceback" not in text, text
    assert names in text, text
    if flags == ["--probe", "64"]:
        assert "--scene" in text, text
    assert "no answer" not in text  # refused before any connection


@pytest.mark.parametrize(
    "overrides, field, flag",
    [
        (["--set", "probe_size=128"], "hello.config.probe.size", "--probe"),
        (["--set", "probe=false"], "hello.config.probe", "--probe"),
    ],
)
def test_the_servers_refusal_is_one_line_naming_the_flag(
    make_server, tmp_path, capsys, overrides, field, flag
):
    server = make_server()
    argv = ["stream", "synthetic", "--max-frames", "1", "--size", "64x48"]
    argv += ["--server", server.connect_address, "--probe", "64", "--probe-at", "0,0,1"]
    code, text = run_cli(argv + overrides, capsys)
    assert code == 2 and "Traceback" not in text, text
    errors = [line for line in text.splitlines() if "error" in line]
    assert len(errors) == 1, text
    assert f"bad_field ({field}, see {flag})" in errors[0], errors


def test_a_panorama_only_source_has_no_room_for_a_probe(tmp_path, capsys):
    import cv2

    image = tmp_path / "pano.png"
    cv2.imwrite(str(image), np.full((32, 64, 3), 128, np.uint8))
    argv = ["stream", str(image), *NOWHERE, "--probe", "32", "--probe-at", "0,0,1"]
    code, text = run_cli(argv, capsys)
    assert code == 2 and "Traceback" not in text, text
    assert "--probe: SOURCE" in text and "panorama only" in text, text


def _args(**given) -> argparse.Namespace:
    base = dict(probe=None, probe_at=None, probe_mips=False, probe_out=None, probe_layout="world")
    return argparse.Namespace(**{**base, **given})


class TestProbeRequest:
    def test_the_flags_make_the_hellos_request(self):
        got = probe_request(
            _args(probe=128, probe_at=(0.0, 1.0, 2.0), probe_mips=True), None, False
        )
        assert got == ProbeRequest(128, (0.0, 1.0, 2.0), True)
        assert probe_request(_args(), None, False) is None

    def test_a_scene_gives_the_point(self):
        assert probe_request(_args(probe=64), None, True) == ProbeRequest(64, None, False)

    def test_a_recordings_request_is_kept_unless_the_flags_say_otherwise(self):
        recorded = SessionConfig("r", probe=ProbeRequest(32, (0.0, 0.0, 1.0), True))
        assert probe_request(_args(probe_out="d"), recorded, False) == recorded.probe
        assert probe_request(_args(probe=64, probe_at=(1.0, 0.0, 0.0)), recorded, False) == (
            ProbeRequest(64, (1.0, 0.0, 0.0), False)
        )
        with pytest.raises(BadInput, match="--probe-at"):
            probe_request(_args(), SessionConfig("r", probe=ProbeRequest(32)), False)
