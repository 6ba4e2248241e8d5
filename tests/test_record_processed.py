"""`arlight stream --record FILE --record-processed` (issue 34, item 5): a live stream
records the frames the server processed, each beside its Result, not every camera frame,
and says how large the file grew per minute."""

from __future__ import annotations

import re

import msgpack
from conftest import run_cli
from streaming_support import identity_step

from arlight.protocols import peek_header
from arlight.sources.recording import FRAME_TOPIC

LIGHTING_TOPIC = "/arlight/lighting"


def _recorded(path) -> tuple[list[int], int]:
    """(seq of every recorded frame, number of Results recorded)."""
    from mcap.reader import make_reader

    seqs, results = [], 0
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic == FRAME_TOPIC:
                seqs.append(int(peek_header(msgpack.unpackb(message.data))["seq"]))
            elif channel.topic == LIGHTING_TOPIC:
                results += 1
    return seqs, results


def _stream(server, path, capsys, *flags: str) -> str:
    code, text = run_cli(
        [
            "stream",
            "synthetic",
            "--size",
            "64x48",
            "--max-frames",
            "40",
            "--mode",
            "live",
            "--server",
            server.connect_address,
            "--record",
            str(path),
            *flags,
        ],
        capsys,
    )
    assert code == 0, text
    return text


def test_live_records_only_what_the_server_processed(make_server, tmp_path, capsys):
    """The server takes ~1 frame in 4 (0.12 s a frame against 30 fps): the processed
    recording holds exactly the Results' frames; the whole one every frame sent."""
    server = make_server(process=identity_step(0.12))
    text = _stream(server, tmp_path / "processed.mcap", capsys, "--record-processed")
    seqs, results = _recorded(tmp_path / "processed.mcap")
    answered = [int(m) - 1 for m in re.findall(r"\[\s*(\d+)/40\] light", text)]
    assert seqs == answered and results == len(answered), (seqs, answered)
    assert 2 <= len(seqs) < 30, seqs  # most frames were dropped by the live server
    assert re.search(r"recorded \d+ frames? to .*MiB per minute\)", text), text
    whole = tmp_path / "whole.mcap"
    _stream(make_server(process=identity_step(0.12)), whole, capsys)
    every, _ = _recorded(whole)
    assert len(every) == 40 > len(seqs)
    assert whole.stat().st_size > (tmp_path / "processed.mcap").stat().st_size


def test_record_processed_needs_record(capsys):
    code, text = run_cli(["stream", "synthetic", "--record-processed"], capsys)
    assert code == 2 and "--record" in text and "Traceback" not in text, text


def test_frames_wait_for_late_results(tmp_path):
    """A live server answers seconds late: at 30 fps hundreds of frames wait for their
    Result; each answered one is written however many came after it (the first version
    held 256 frames and lost half of a 320x240 session's processed frames)."""
    from conftest import result
    from streaming_support import frame_parts

    from arlight.client.recording import ProcessedRecorder, Recorder
    from arlight.protocols import received_record

    path = tmp_path / "late.mcap"
    rec = ProcessedRecorder(Recorder(path, frames=True))
    for seq in range(600):
        rec.write_frame(frame_parts(seq), 10**9 + seq)
    for seq in (10, 300, 590):
        r = result(seq=seq)
        rec.write_result(r, received_record(r, 1.0))
    rec.close()
    seqs, results = _recorded(path)
    assert seqs == [10, 300, 590] and results == 3
    assert rec.skipped == 597

    small = ProcessedRecorder(Recorder(tmp_path / "small.mcap"), hold_bytes=1)
    for seq in range(3):
        small.write_frame(frame_parts(seq), 10**9 + seq)
    r = result(seq=2)
    small.write_result(r, received_record(r, 1.0))  # the newest frame always waits
    small.close()
    assert _recorded(tmp_path / "small.mcap")[0] == [2]
