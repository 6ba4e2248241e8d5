"""arlight.offline: the estimate loop `arlight estimate` and `arlight batch` share, the JSON
record of a frame (the server's, byte for byte), recordings read without a server, and the
notes a terminal prints for a frame without depth or with a low confidence."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from arlight.cli import main
from arlight.core.frames import FrameInput
from arlight.offline import FrameNotes, estimate_frames, has_usable_depth, open_recording
from arlight.pipeline.config import Config
from arlight.pipeline.light_confidence import LOW_CONFIDENCE
from arlight.pipeline.pipeline import Pipeline
from arlight.sources.recording import RecordingError
from arlight.sources.sequence import open_sequence
from arlight.sources.synthetic import make_sequence

SIZE = (64, 48)


def write_tum(folder: Path, n: int = 2) -> Path:
    """The built-in scene as a TUM RGB-D folder with camera.json."""
    seq = make_sequence(num_frames=n, width=SIZE[0], height=SIZE[1])
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    assoc = []
    for i, f in enumerate(seq.frames):
        assert cv2.imwrite(str(folder / "rgb" / f"{i}.png"), f.color[..., ::-1])
        assert cv2.imwrite(str(folder / "depth" / f"{i}.png"), f.depth)
        assoc.append(f"{f.timestamp:.6f} rgb/{i}.png {f.timestamp:.6f} depth/{i}.png")
    (folder / "associations.txt").write_text("\n".join(assoc) + "\n")
    c = seq.camera
    (folder / "camera.json").write_text(
        json.dumps(
            {
                "fx": c.fx,
                "fy": c.fy,
                "cx": c.cx,
                "cy": c.cy,
                "width": c.width,
                "height": c.height,
                "depth_scale": float(seq.frames[0].depth_scale),
            }
        )
    )
    return folder


@pytest.fixture(scope="module")
def streams(tmp_path_factory):
    """A TUM folder and its lossless recording (PNG colour: the folder's pixels)."""
    d = tmp_path_factory.mktemp("offline")
    folder = write_tum(d / "scene")
    recording = d / "scene.mcap"
    assert (
        main(
            [
                "record",
                str(folder),
                "--out",
                str(recording),
                "--mode",
                "lossless",
                "--color-codec",
                "png",
            ]
        )
        == 0
    )
    return folder, recording


class TestFrameRecord:
    @pytest.mark.parametrize(("rgb", "exports"), [(False, ()), (True, ("arcore", "unity"))])
    def test_equals_the_servers_record_byte_for_byte(self, rgb, exports):
        """The record built without the server is the one the server's Result gave
        (the server's Result of it, as `arlight stream --out` writes it)."""
        from arlight.protocols import result_record
        from arlight.server.results import result_message

        seq = make_sequence(num_frames=2, width=96, height=72)
        pipeline = Pipeline(Config.from_preset("fast", estimate_rgb=rgb), seq.camera)
        done = list(estimate_frames(pipeline, seq.frames, exports))
        assert [d.index for d in done] == [0, 1]
        for d in done:
            want = result_record(
                result_message(
                    d.result,
                    seq=d.index,
                    counters=(d.index + 1, d.index + 1, 0),
                    receive_time_wall=0.0,
                    finish_time_wall=0.0,
                    exports=exports,
                )
            )
            assert json.dumps(d.record) == json.dumps(want)
            assert ("exports" in d.record) == bool(exports)
            assert (d.record["sh_rgb"] is not None) == rgb
            assert d.process_ms > 0


class TestOpenRecording:
    def test_frames_are_the_folders(self, streams):
        folder, recording = streams
        camera, n, frames = open_recording(str(recording))
        seq = open_sequence(str(folder), use_poses=False)
        assert n == len(seq.frames) == 2
        assert (camera.width, camera.height, camera.fx) == (
            seq.camera.width,
            seq.camera.height,
            seq.camera.fx,
        )
        for got, want in zip(frames, seq.frames, strict=True):
            assert np.array_equal(got.color, want.color)
            assert np.array_equal(got.depth, want.depth)
            assert got.depth_scale == want.depth_scale and got.pose is None

    def test_max_frames(self, streams):
        _, n, frames = open_recording(str(streams[1]), max_frames=1)
        assert n == 1 and len(list(frames)) == 1

    def test_not_a_recording(self, tmp_path):
        bad = tmp_path / "x.mcap"
        bad.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
        with pytest.raises(RecordingError, match="x.mcap"):
            open_recording(str(bad))

    def test_the_offline_path_never_imports_the_server(self, streams, tmp_path):
        """`arlight batch`'s per-stream work (a folder and a recording) in a fresh process."""
        folder, recording = streams
        code = (
            "import sys\n"
            "from arlight.batch import BatchOptions, process_stream\n"
            "options = BatchOptions(preset='fast', max_frames=1)\n"
            f"for path, out in (({str(folder)!r}, {str(tmp_path / 'a.jsonl')!r}),\n"
            f"                  ({str(recording)!r}, {str(tmp_path / 'b.jsonl')!r})):\n"
            "    assert process_stream(path, out, options).frames == 1\n"
            "bad = sorted(m for m in sys.modules if m.startswith('arlight.server'))\n"
            "print(bad); sys.exit(1 if bad else 0)\n"
        )
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 0, done.stdout + done.stderr


class TestFrameNotes:
    def test_a_frame_without_depth_is_named_every_time(self):
        notes = FrameNotes()
        for _ in range(2):
            assert "no usable depth" in notes.note(0.0, "no valid depth", depth_usable=False)
        assert notes.summary() == "2 of 2 frames without usable depth"

    def test_a_low_confidence_gives_its_reason_where_its_causes_change(self):
        notes = FrameNotes()
        low = LOW_CONFIDENCE / 2
        first = notes.note(low, "few normal directions (spread 0.07)")
        assert first == (
            f"low confidence {low:.2f} (below {LOW_CONFIDENCE:g}): "
            "few normal directions (spread 0.07)"
        )
        assert notes.note(low, "few normal directions (spread 0.09)") is None  # same causes
        assert "jumped" in notes.note(low, "few normal directions (spread 0.09); jumped 9 deg")
        assert notes.note(0.9, "") is None
        assert (
            notes.note(low, "") == f"low confidence {low:.2f} (below "
            f"{LOW_CONFIDENCE:g}): no reason recorded"
        )
        assert notes.summary().startswith(
            f"4 of 5 frames with a confidence below {LOW_CONFIDENCE:g}"
        )

    def test_nothing_to_say(self):
        notes = FrameNotes()
        assert notes.note(1.0, "") is None and notes.summary() is None

    def test_usable_depth(self):
        color = np.zeros((2, 2, 3), np.uint8)
        assert not has_usable_depth(FrameInput(color, np.zeros((2, 2), np.uint16)))
        assert not has_usable_depth(FrameInput(color, np.full((2, 2), np.nan, np.float32)))
        assert has_usable_depth(FrameInput(color, np.array([[0, 0], [0, 1200]], np.uint16)))


def test_overlapped_estimate_yields_every_frame_with_its_input():
    """estimate_frames(overlap=True): each frame's result beside that frame, in order."""
    seq = make_sequence(num_frames=4, width=96, height=72)
    done = list(
        estimate_frames(Pipeline(Config.from_preset("fast"), seq.camera), seq.frames, (), True)
    )
    assert [d.index for d in done] == [0, 1, 2, 3]
    for d, frame in zip(done, seq.frames, strict=True):
        assert d.frame is frame and d.result.timestamp == frame.timestamp
        assert d.process_ms >= 0.0


def test_estimate_overlap_flag_runs(tmp_path):
    out = tmp_path / "light.jsonl"
    rc = main(["estimate", "--preset", "fast", "--max-frames", "3", "--overlap", "--out", str(out)])
    assert rc == 0
    assert len(out.read_text().splitlines()) == 3
