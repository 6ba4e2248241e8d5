"""`arlight serve --ray`: sessions' pipelines in Ray actors, a lost actor loses no frame.

A real server on loopback with the compute step on one local Ray (2 CPUs, shared by the
module), real capture clients streaming the built-in synthetic scene (64x48, ground-truth
poses) losslessly. Killing a session's actor mid-stream (`ray.kill`) must cost nothing: every
frame gets exactly one Result, the lost ones resent by the client after the retryable
`pipeline_lost` Error, processed by a new actor.
"""

from __future__ import annotations

import collections
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from conftest import SMALL
from streaming_support import CaptureClientThread, server_options, wait_for

from arlight.batch import init_local_ray
from arlight.cli import EXIT_BAD_INPUT, main
from arlight.client.capture import CaptureClient, StreamOptions
from arlight.protocols import ErrorField
from arlight.server.server import Server
from arlight.sources.source import open_source

ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'arlight[ray]'")

FRAMES = 10
SIZE = (64, 48)


@pytest.fixture(scope="module")
def local_ray():
    init_local_ray(ray, num_cpus=2)  # its servers on loopback only (issue 39)
    yield
    ray.shutdown()


@pytest.fixture
def ray_server(local_ray):
    from arlight.ray_serve import RayCompute

    compute = RayCompute(ray)
    server = Server(server_options(), process=compute).start()
    yield server, compute
    server.stop(timeout=15)
    compute.close()


def capture(server, session: str, on_result=None, frames: int = FRAMES) -> CaptureClient:
    source = open_source("synthetic", use_poses=True, max_frames=frames, synthetic_size=SIZE)
    options = StreamOptions(
        server=server.connect_address,
        session=session,
        mode="lossless",
        rate="max",
        preset="fast",
        overrides=dict(SMALL),
    )
    return CaptureClient(source, options, on_result=on_result)


def received(seqs: list[int], n: int) -> None:
    counts = collections.Counter(seqs)
    assert sorted(counts) == list(range(n)), f"missing: {set(range(n)) - set(counts)}"
    assert max(counts.values()) == 1, f"duplicates: {[s for s, c in counts.items() if c > 1]}"


def test_two_sessions_each_on_its_own_actor(ray_server):
    server, compute = ray_server
    seqs = {"a": [], "b": []}
    actors = {}

    def on_result(name):
        def record(result, _wall):
            seqs[name].append(result.seq)
            session = server.sessions.get(name)
            if session is not None and compute.actor(session) is not None:
                actors[name] = compute.actor(session)

        return record

    threads = [CaptureClientThread(capture(server, n, on_result(n))) for n in seqs]
    for t in threads:
        t.start()
    summaries = [t.join(120) for t in threads]
    for name, summary in zip(seqs, summaries, strict=True):
        assert summary.results == FRAMES and not summary.errors, summary.errors
        received(seqs[name], FRAMES)
    assert len({a._actor_id for a in actors.values()}) == 2  # one actor per session
    # the sessions closed at the end of the stream: their actors were killed
    wait_for(lambda: not compute._actors, 10, "the actors to be released")
    assert compute.actors_lost == 0


def test_a_killed_actor_loses_no_frame(ray_server, caplog):
    server, compute = ray_server
    caplog.set_level(logging.INFO, logger="arlight.server")
    seqs: list[int] = []
    killed: list = []
    errors = []
    kill_after = 3

    def on_result(result, _wall):
        seqs.append(result.seq)
        if len(seqs) == kill_after:  # mid-stream: frames queued and in the actor
            actor = compute.actor(server.sessions["k"])
            killed.append(actor)
            threading.Thread(target=ray.kill, args=(actor,), daemon=True).start()

    client = capture(server, "k", on_result)
    client.on_error = errors.append
    thread = CaptureClientThread(client)
    thread.start()
    summary = thread.join(180)
    assert killed, "the stream ended before the actor was killed"
    received(seqs, FRAMES)  # every frame once: nothing lost, no duplicates
    assert summary.results == FRAMES and not summary.errors
    assert compute.actors_lost >= 1
    text = caplog.text
    assert "its Ray actor was lost" in text and "pipeline lost at frame" in text
    # the frames lost with the actor were reported retryable (pipeline_lost), not final
    assert server.stats.error_codes["bad_state"] >= 1
    assert not errors  # retryable Errors are not the client's errors


def test_pipeline_lost_is_retryable_in_the_protocol():
    from arlight.protocols import Error, decode, encode

    error = Error(
        code="bad_state", field=ErrorField.PIPELINE_LOST, seq=7, retryable=True, message="lost"
    )
    assert decode(encode(error)) == error


def test_without_ray_serve_exits_2_naming_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    assert main(["serve", "--ray"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "pip install 'arlight[ray]'" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("address", "says"),
    [
        ("not an address", "--ray expects"),
        ("127.0.0.1:1", "no Ray cluster answers there"),
    ],
)
def test_bad_address_exits_2(address, says, capsys, monkeypatch):
    monkeypatch.setattr(ray, "is_initialized", lambda: False)  # as in a fresh process
    assert main(["serve", "--ray", address]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


def test_arlight_serve_ray_local_end_to_end(tmp_path):
    """The command itself: `arlight serve --ray local` starts its own Ray, serves a lossless
    stream, stops on SIGTERM (actors killed, Ray shut down) with exit code 0."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log_path = tmp_path / "serve.log"
    env = {**os.environ, "RAY_ADDRESS": ""}
    with open(log_path, "w") as log_file:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "arlight.cli",
                "serve",
                "--ray",
                "local",
                "--bind",
                f"tcp://127.0.0.1:{port}",
                "--heartbeat",
                "0.5",
            ],
            stdout=log_file,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        deadline = time.monotonic() + 60
        while "listening on" not in log_path.read_text():
            assert proc.poll() is None, log_path.read_text()
            assert time.monotonic() < deadline, "serve --ray did not start"
            time.sleep(0.2)
        source = open_source("synthetic", use_poses=True, max_frames=4, synthetic_size=SIZE)
        options = StreamOptions(
            server=f"tcp://127.0.0.1:{port}",
            session="cli",
            mode="lossless",
            rate="max",
            preset="fast",
            overrides=dict(SMALL),
        )
        seqs = []
        thread = CaptureClientThread(
            CaptureClient(source, options, on_result=lambda r, _w: seqs.append(r.seq))
        )
        thread.start()
        summary = thread.join(120)
        assert summary.results == 4 and not summary.errors
        received(seqs, 4)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    text = log_path.read_text()
    assert code == 0, text
    assert "pipeline in Ray actor" in text and "Traceback" not in text
