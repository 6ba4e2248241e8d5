"""SIGTERM (what `docker stop`, systemd and `timeout` send) mid-run finalises every file a
client writes, and Results reach disk as they arrive (issue 34, item 2).

Each test runs the real `arlight` command as a subprocess against a loopback server (a
compute step standing in for the Pipeline, streaming_support.identity_step), waits until
its files show progress, sends SIGTERM and reads every file back: the MCAP with the `mcap`
reader (summary and footer present, every message readable), the JSON lines, the PNGs and
the mp4.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from streaming_support import identity_step

from arlight.sources.recording import FRAME_TOPIC

WAIT_S = 60.0  # for the first lines (a fresh interpreter imports numpy, OpenCV, Open3D)


def _start(argv: list[str], cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "arlight.cli", *argv],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.exists() else []


def _wait_for(what, proc: subprocess.Popen, timeout_s: float = WAIT_S) -> None:
    """Poll what() until true; fail with the process's output if it ends or times out."""
    deadline = time.monotonic() + timeout_s
    while not what():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"no progress (rc {proc.returncode}):\n{out[-2000:]}\n{err[-3000:]}")
        time.sleep(0.1)


def _terminate(proc: subprocess.Popen, signum: int = signal.SIGTERM) -> tuple[int, str]:
    proc.send_signal(signum)
    try:
        out, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"SIGTERM did not end it:\n{err[-3000:]}")
    assert "Traceback" not in err, err
    return proc.returncode, out + err


def _read_mcap(path: Path) -> dict[str, int]:
    """Messages per topic, read through the summary (which SIGTERM used to leave out)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, f"{path}: no summary"
        counts: dict[str, int] = {}
        for _, channel, message in reader.iter_messages():
            assert message.data  # every message readable, decompressed
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
        assert sum(counts.values()) == summary.statistics.message_count
    return counts


def _jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in _lines(path)]  # every line whole


@pytest.fixture()
def server(make_server):
    return make_server(process=identity_step(0.02))


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["TERM", "INT"])
def test_stream_out_and_record_survive_sigterm(server, tmp_path, signum):
    """A 100000-frame synthetic stream starts at once (frames rendered as sent), its Results
    are on disk while it runs, and SIGTERM (or Ctrl-C's SIGINT) leaves a complete MCAP."""
    out, rec = tmp_path / "results.jsonl", tmp_path / "stream.mcap"
    proc = _start(
        [
            "stream",
            "synthetic",
            "--size",
            "64x48",
            "--max-frames",
            "100000",
            "--server",
            server.connect_address,
            "--mode",
            "lossless",
            "--out",
            str(out),
            "--record",
            str(rec),
        ],
        tmp_path,
    )
    _wait_for(lambda: len(_lines(out)) >= 5, proc)  # 100000 frames render in ~1 h
    code, text = _terminate(proc, signum)
    assert code == 130, text
    results = _jsonl(out)
    counts = _read_mcap(rec)
    assert counts[FRAME_TOPIC] >= len(results) >= 5
    assert counts["/arlight/lighting"] == len(results), counts  # each Result recorded


def test_record_survives_sigterm(tmp_path):
    rec = tmp_path / "record.mcap"
    proc = _start(
        ["record", "synthetic", "--size", "64x48", "--max-frames", "100000", "--out", str(rec)],
        tmp_path,
    )
    assert proc.stdout is not None
    _wait_for(lambda: "[    5/" in proc.stdout.readline(), proc)
    code, text = _terminate(proc)
    assert code == 130, text
    assert _read_mcap(rec)[FRAME_TOPIC] >= 5


def test_display_record_survives_sigterm(server, tmp_path):
    """A display writing every kind of file (MCAP, JSON lines, PNG folder, mp4) stopped by
    SIGTERM mid-session: each is whole. The stream ends afterwards by its own SIGTERM."""
    rec, out, video = tmp_path / "display.mcap", tmp_path / "out", tmp_path / "display.mp4"
    display = _start(
        [
            "display",
            "--server",
            server.connect_address,
            "--session",
            "sig",
            "--record",
            str(rec),
            "--out",
            str(out),
            "--video",
            str(video),
            "--follow",
        ],
        tmp_path,
    )
    stream = _start(
        [
            "stream",
            "synthetic",
            "--size",
            "64x48",
            "--max-frames",
            "100000",
            "--session",
            "sig",
            "--composite",
            "--server",
            server.connect_address,
        ],
        tmp_path,
    )
    try:
        _wait_for(lambda: len(_lines(out / "results.jsonl")) >= 5, display)
        code, text = _terminate(display)
    finally:
        _terminate(stream)
    assert code == 130, text
    results = _jsonl(out / "results.jsonl")
    assert _read_mcap(rec)["/arlight/lighting"] >= len(results) >= 5
    pngs = sorted((out / "frames").glob("*.png"))
    assert pngs and all(cv2.imread(str(p)) is not None for p in pngs)
    capture = cv2.VideoCapture(str(video))
    ok, first = capture.read()
    capture.release()
    assert ok and first.shape[:2] == (48, 64), "the mp4 has no readable frame"


def _redwood_folder(path: Path, frames: int) -> Path:
    """A small Open3D/Redwood folder (color/, depth/ in millimetres) of `frames` frames."""
    from arlight.sources.synthetic import make_sequence

    seq = make_sequence(num_frames=2, width=64, height=48)
    (path / "color").mkdir(parents=True)
    (path / "depth").mkdir()
    for i in range(frames):
        f = seq.frames[i % 2]
        mm = np.round(f.depth.astype(np.float64) / f.depth_scale * 1000.0).astype(np.uint16)
        cv2.imwrite(str(path / "color" / f"{i:06d}.png"), f.color[..., ::-1])
        cv2.imwrite(str(path / "depth" / f"{i:06d}.png"), mm)
    return path


def test_estimate_out_survives_sigterm(tmp_path):
    data = _redwood_folder(tmp_path / "seq", 400)
    out, composites = tmp_path / "estimate.jsonl", tmp_path / "composites"
    proc = _start(
        [
            "--open3d-threads",
            "1",
            "estimate",
            str(data),
            "--preset",
            "fast",
            "--out",
            str(out),
            "--composite-out",
            str(composites),
        ],
        tmp_path,
    )
    _wait_for(lambda: len(_lines(out)) >= 3, proc, timeout_s=120.0)
    code, text = _terminate(proc)
    assert code == 130, text
    records = _jsonl(out)
    assert 3 <= len(records) < 400
    pngs = sorted(composites.glob("*.png"))
    assert len(pngs) >= len(records) - 1 and all(cv2.imread(str(p)) is not None for p in pngs)


def test_a_stop_signal_waits_for_the_record_being_written():
    """A signal inside `uninterrupted()` (a Recorder writing one MCAP record) takes effect at
    the block's end, so the summary written on the way out follows whole records."""
    from arlight.cli.stop_signals import terminate_as_interrupt
    from arlight.client.stop_signals import uninterrupted

    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    steps = []
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"), terminate_as_interrupt():
        with uninterrupted():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler has run by now
            steps.append("record finished")
        steps.append("after the record")  # never reached
    assert steps == ["record finished"]
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
