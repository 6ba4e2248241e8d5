"""The streaming server over real loopback sockets: delivery modes, sessions, displays,
liveness, restarts, shutdown and hostile input (issue 3, item 5)."""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq
from streaming_support import (
    SMALL,
    TUM_FOLDER,
    CaptureClientThread,
    CuttableProxy,
    RawPeer,
    flat_source,
    identity_step,
    need_data,
    run_with_timeout,
    server_factory,
    wait_for,
)

from arlight.client.capture import (
    CaptureClient,
    StreamError,
    StreamOptions,
    stream,
)
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.pipeline.config import Config
from arlight.pipeline.frames import FrameInput
from arlight.pipeline.pipeline import FrameError, Pipeline
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    Error,
    Frame,
    Hello,
    Result,
    SceneObjectSpec,
    SceneSpec,
    SessionConfig,
    Welcome,
    decode,
    encode,
)
from arlight.server.server import Server, ServerOptions
from arlight.sources.source import open_source, sequence_source
from arlight.sources.synthetic import make_sequence


@pytest.fixture
def make_server():
    yield from server_factory()


def _assert_result_equals(result: Result, expected) -> None:
    """A Result carries exactly what Pipeline.process returned (float64 through msgpack)."""
    np.testing.assert_array_equal(result.sh, expected.sh)
    np.testing.assert_array_equal(
        result.dominant_direction_world, expected.dominant_direction_world
    )
    np.testing.assert_array_equal(
        result.dominant_direction_camera, expected.dominant_direction_camera
    )
    assert result.intensity == expected.intensity
    assert result.confidence == expected.confidence  # the same type on both sides
    assert result.confidence_map == expected.confidence.to_dict()  # as on the wire
    np.testing.assert_array_equal(result.pose, expected.pose)


def _wire_input(frame) -> FrameInput:
    """The pipeline input a SourceFrame becomes on the server (uint16 at 5000 units per
    metre, converted to metres by Pipeline.process)."""
    return FrameInput(
        color=frame.color,
        depth=frame.depth,
        depth_scale=5000.0,
        timestamp=frame.timestamp,
        pose=frame.pose,
    )


class TestLossless:
    @pytest.mark.data
    def test_tum_folder_every_frame_equal_to_pipeline(self, make_server):
        """A TUM folder streamed losslessly: one Result per frame, in order, each equal to
        Pipeline.process on the frames the data set reader gives (png colour, zstd depth)."""
        from arlight.sources.sequence import open_sequence

        folder = need_data(TUM_FOLDER)
        server = make_server()
        source = open_source(str(folder), max_frames=4)
        assert source.depth_scale == 5000.0  # TUM's integers, so metres survive bit for bit
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address,
            session="tum",
            mode="lossless",
            rate="max",
            color_codec="png",
            depth_codec="zstd",
            preset="fast",
            overrides=SMALL,
        )
        summary = run_with_timeout(
            lambda: stream(source, options, on_result=lambda r, _: results.append(r))
        )
        assert summary.errors == []
        assert [r.seq for r in results] == [0, 1, 2, 3]
        sequence = open_sequence(folder, max_frames=4)
        pipeline = Pipeline(Config.from_preset("fast", **SMALL), sequence.camera)
        for result, frame in zip(results, sequence.frames, strict=True):
            assert result.timestamp == frame.timestamp  # lossless keeps the source's clock
            _assert_result_equals(result, pipeline.process(frame))
        assert results[-1].frames_received == results[-1].frames_processed == 4
        assert results[-1].frames_dropped == 0

    def test_two_concurrent_sessions_never_mix(self, make_server):
        """Two sessions streamed at once, each equal to its own Pipeline run alone."""
        server = make_server(workers=2)
        sources = {}
        for name, seed in (("left", 0), ("right", 3)):
            seq = make_sequence(num_frames=3, width=160, height=120, seed=seed)
            sources[name] = sequence_source(name, seq.camera, seq.frames)
        results: dict[str, list[Result]] = {"left": [], "right": []}
        clients = [
            CaptureClientThread(
                CaptureClient(
                    sources[name],
                    StreamOptions(
                        server=server.connect_address,
                        session=name,
                        mode="lossless",
                        rate="max",
                        color_codec="png",
                        preset="fast",
                        overrides=SMALL,
                    ),
                    on_result=lambda r, _, name=name: results[name].append(r),
                )
            )
            for name in sources
        ]
        for client in clients:
            client.start()
        for client in clients:
            summary = client.join()
            assert summary.errors == [] and summary.results == 3
        for name, source in sources.items():
            pipeline = Pipeline(Config.from_preset("fast", **SMALL), server_camera(source))
            got = results[name]
            assert [r.seq for r in got] == [0, 1, 2]
            for result, frame in zip(got, source.frames(), strict=True):
                _assert_result_equals(result, pipeline.process(_wire_input(frame)))

    def test_duplicate_seq_is_not_processed_again(self, make_server):
        """A frame sent again (a client resending after a reconnect) gets the cached Result."""
        server = make_server(process=identity_step())
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("dup"), Welcome)
        parts = _frame_parts(seq=0, value=42)
        peer.send(parts)
        first = peer.receive_raw()
        peer.send(parts)
        again = peer.receive_raw()
        assert again == first
        counters = server.snapshot()["sessions"]["dup"]
        assert counters["frames_received"] == counters["frames_processed"] == 1
        peer.close()

    def test_final_error_lost_while_detached_is_sent_again_for_the_duplicate(self, make_server):
        """A frame's final Error that never reached its client (the client disconnected
        before it was sent) is sent again when the reconnected client resends the frame, as a
        Result is; the server used to answer nothing and a lossless client waited forever."""
        gate = threading.Event()
        step = identity_step()

        def process(frame, session, render_light, deadline):
            assert gate.wait(10)
            return step(frame, session, render_light, deadline)

        server = make_server(process=process, heartbeat_interval_s=5.0)  # raw peers: no beats
        first = RawPeer(server.connect_address)
        assert isinstance(first.hello("lost-error"), Welcome)
        good, bad = _frame_parts(seq=0, value=21), _frame_parts(seq=1, width=32, height=24)
        first.send(good)  # held in the worker until the client is gone
        first.send(bad)  # fails validation in the worker: a final Error
        wait_for(
            lambda: server.snapshot()["sessions"]["lost-error"]["frames_received"] == 2,
            10,
            what="both frames received",
        )
        first.close()
        gate.set()
        wait_for(
            lambda: server.stats.error_codes["bad_field"] == 1,
            10,
            what="the Error to be sent to the departed client",
        )
        second = RawPeer(server.connect_address)  # the client again, on a new connection
        assert isinstance(second.hello("lost-error"), Welcome)  # resumes the session
        second.send(good)
        second.send(bad)
        result = second.receive()
        assert isinstance(result, Result) and result.seq == 0
        assert result.sh[0] == pytest.approx(21.0)
        error = second.receive_raw()
        decoded = decode(error)
        assert isinstance(decoded, Error) and decoded.seq == 1
        assert (decoded.code, decoded.field) == ("bad_field", "frame.color")
        second.send(bad)  # a third time: the same bytes again
        assert second.receive_raw() == error
        counters = server.snapshot()["sessions"]["lost-error"]
        assert counters["frames_received"] == 2  # neither frame was processed twice
        assert counters["frames_processed"] == 1 and counters["frames_failed"] == 1
        second.close()

    def test_stream_completes_when_a_final_error_is_lost_in_a_network_drop(self, make_server):
        """CaptureClient end to end: the connection drops while a frame that will fail is in
        a worker, so its Error is lost; the client reconnects, resends its unacknowledged
        frames, gets the Error again and the lossless stream completes (it used to hang)."""
        bad_seq, n = 3, 8
        at_bad, go = threading.Event(), threading.Event()
        calls: collections.Counter = collections.Counter()
        step = identity_step()

        def process(frame, session, render_light, deadline):
            seq = int(round(float(frame.color[0, 0, 0]))) - 10  # flat_source: 10 + i
            calls[seq] += 1
            if seq == bad_seq:
                at_bad.set()
                assert go.wait(10)
                raise FrameError("pose", "not a rigid transform (test)")
            return step(frame, session, render_light, deadline)

        server = make_server(process=process)
        proxy = CuttableProxy(server.port)
        seqs: list[int] = []
        client = CaptureClient(
            flat_source(n),
            StreamOptions(
                server=proxy.address,
                session="dropped",
                mode="lossless",
                rate="max",
                color_codec="png",
                reconnect_timeout_s=20.0,
            ),
            on_result=lambda r, _: seqs.append(r.seq),
        )
        runner = CaptureClientThread(client)
        try:
            runner.start()
            assert at_bad.wait(30)
            proxy.cut()  # the network drops while frame 3 is in the worker ...
            go.set()  # ... so its Error (and the next Results) go to a peer that is gone
            wait_for(
                lambda: server.stats.error_codes["bad_field"] == 1,
                10,
                what="the Error to be sent into the void",
            )
            proxy.release()
            summary = runner.join(30)
        finally:
            go.set()
            proxy.close()
        assert summary.reconnects >= 1
        assert seqs == [s for s in range(n) if s != bad_seq]  # each once, in order
        assert [(e.seq, e.code, e.field) for e in summary.errors] == [
            (bad_seq, "bad_field", "frame.pose")
        ]
        assert all(calls[s] == 1 for s in range(n)) and sum(calls.values()) == n

    def test_duplicate_older_than_the_cache_gets_a_final_error(self, make_server):
        """A resent frame whose outcome the server no longer keeps gets a definite answer,
        bad_state "duplicate" (it used to get none); recent ones get their Result again."""
        server = make_server(process=identity_step(), credits=1, heartbeat_interval_s=5.0)
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("old"), Welcome)
        replies = {}
        for seq in (0, 1, 2, 3, 4, 5, 6, 9):  # 1 + 4 outcomes are kept: 3..6 and 9
            peer.send(_frame_parts(seq=seq, value=seq))
            replies[seq] = peer.receive_raw()
        for seq in (6, 3):
            peer.send(_frame_parts(seq=seq, value=seq))
            assert peer.receive_raw() == replies[seq]
        for seq in (0, 2, 8):  # too old, or never accepted and below the highest seq
            peer.send(_frame_parts(seq=seq, value=seq))
            error = peer.receive()
            assert isinstance(error, Error) and error.seq == seq, error
            assert (error.code, error.field) == ("bad_state", "duplicate"), error
        counters = server.snapshot()["sessions"]["old"]
        assert counters["frames_received"] == counters["frames_processed"] == 8
        peer.close()

    def test_duplicate_of_a_waiting_frame_is_answered_once_when_it_finishes(self, make_server):
        gate = threading.Event()
        step = identity_step()

        def process(frame, session, render_light, deadline):
            assert gate.wait(10)
            return step(frame, session, render_light, deadline)

        server = make_server(process=process, heartbeat_interval_s=5.0)
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("waiting"), Welcome)
        for seq in (0, 1, 0, 1):  # 0 in the worker, 1 queued, then both again
            peer.send(_frame_parts(seq=seq, value=seq))
        wait_for(lambda: server.stats.messages >= 5, 10, what="all frames read")
        gate.set()
        assert [peer.receive().seq for _ in range(2)] == [0, 1]
        assert not peer.socket.poll(500)  # nothing more: one answer per frame
        peer.close()

    def test_restarted_client_resuming_a_session_gets_an_answer_for_every_frame(
        self, make_server, caplog
    ):
        """A second client with the same session and config resumes the session and sends
        seqs the server already processed: recent ones get their cached Results, older ones
        the final "duplicate" Error (logged by the client); none is processed again."""
        calls: collections.Counter = collections.Counter()
        step = identity_step()

        def process(frame, session, render_light, deadline):
            calls[int(round(float(frame.color[0, 0, 0]))) - 10] += 1
            return step(frame, session, render_light, deadline)

        server = make_server(process=process, credits=1)
        options = StreamOptions(
            server=server.connect_address,
            session="again",
            mode="lossless",
            rate="max",
            color_codec="png",
        )
        first = CaptureClient(flat_source(8), options)
        first.on_result = lambda r, _: first.stop() if r.seq == 7 else None  # no Bye
        assert run_with_timeout(first.run, 30).results == 8
        second = CaptureClient(flat_source(8), options)
        with caplog.at_level(logging.WARNING, logger="arlight.client.capture"):
            summary = run_with_timeout(second.run, 30, stop=second.stop)
        assert [(e.seq, e.code, e.field) for e in summary.errors] == [
            (s, "bad_state", "duplicate") for s in (0, 1, 2)
        ]
        assert summary.results == 5  # 3..7: the last credits + 4 outcomes
        assert "no longer keeps" in caplog.text
        assert sum(calls.values()) == 8

    def test_client_counts_a_second_answer_to_a_frame_once(self):
        """A frame sent twice may be answered twice (its answer arrived and was also replayed
        for the resent copy): the client acknowledges it, reports it and returns its credit
        once. A hand-written server answers every frame twice, credits 1."""
        router = zmq.Context.instance().socket(zmq.ROUTER)
        router.setsockopt(zmq.LINGER, 0)
        port = router.bind_to_random_port("tcp://127.0.0.1")
        done = threading.Event()

        def serve():
            identity, *parts = router.recv_multipart()
            assert isinstance(decode(parts), Hello)
            router.send_multipart(
                [identity, *encode(Welcome(PROTOCOL_VERSION, "twice", 1, 5.0, "fake"))]
            )
            while not done.is_set():
                if not router.poll(100):
                    continue
                identity, *parts = router.recv_multipart()
                message = decode(parts)
                if not isinstance(message, Frame):
                    continue
                reply = (
                    Error(code="bad_field", message="test", field="frame.pose", seq=message.seq)
                    if message.seq % 2 == 0
                    else Result(
                        seq=message.seq,
                        timestamp=1.0,
                        sh=[0.0],
                        dominant_direction_camera=[0, 0, 1],
                        dominant_direction_world=[0, 0, 1],
                        intensity=0.0,
                        confidence={},
                        pose=np.eye(4).tolist(),
                        timings_ms={},
                        frames_received=0,
                        frames_processed=0,
                        frames_dropped=0,
                        server_receive_time=0.0,
                        server_finish_time=0.0,
                    )
                )
                for _ in range(2):
                    router.send_multipart([identity, *encode(reply)])

        server = threading.Thread(target=serve, daemon=True)
        server.start()
        errors: list[Error] = []
        try:
            summary = run_with_timeout(
                lambda: stream(
                    flat_source(4),
                    StreamOptions(
                        server=f"tcp://127.0.0.1:{port}",
                        session="twice",
                        mode="lossless",
                        rate="max",
                    ),
                    on_error=errors.append,
                ),
                30,
            )
        finally:
            done.set()
            server.join(5)
            router.close(linger=0)
        assert summary.results == 2
        assert [e.seq for e in summary.errors] == [e.seq for e in errors] == [0, 2]

    def test_frames_beyond_the_credit_window_are_refused_then_accepted_in_order(self, make_server):
        server = make_server(
            process=identity_step(delay_s=0.1), credits=2, heartbeat_interval_s=5.0
        )  # the raw peer sends no heartbeats
        peer = RawPeer(server.connect_address)
        assert peer.hello("greedy").credits == 2
        for seq in range(8):  # the queue holds credits + 2 = 4 (and 1 in a worker)
            peer.send(_frame_parts(seq=seq, value=seq))
        refused, done = [], []
        while len(done) < 8:
            message = peer.receive(15)
            if isinstance(message, Error):
                assert (message.code, message.field) == ("bad_state", "credits")
                refused.append(message.seq)
            else:
                done.append(message.seq)
                if len(done) == 5:  # room again: send the refused ones, in order
                    for seq in sorted(refused):
                        peer.send(_frame_parts(seq=seq, value=seq))
        assert refused == [5, 6, 7] and done == list(range(8))
        peer.close()


def server_camera(source):
    from arlight.pipeline.camera import PinholeCamera

    c = source.calibration
    return PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy)


class TestLive:
    def test_fast_producer_drops_frames_and_reports_them(self, make_server):
        server = make_server(process=identity_step(delay_s=0.05))
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address, session="live", mode="live", rate="max"
        )
        summary = run_with_timeout(
            lambda: stream(flat_source(40), options, on_result=lambda r, _: results.append(r))
        )
        assert summary.frames_sent == 40 and summary.frames_not_sent == 0
        last = results[-1]
        assert last.seq == 39  # the newest frame is never dropped
        assert last.frames_received == 40
        assert last.frames_dropped > 0
        assert last.frames_processed + last.frames_dropped == 40
        assert len(results) == last.frames_processed
        assert summary.frames_dropped == last.frames_dropped
        seqs = [r.seq for r in results]
        assert seqs == sorted(seqs)
        for r in results:  # every Result is its own frame's, and reports the counters
            assert r.sh[0] == pytest.approx(10 + r.seq)
            assert r.frames_processed + r.frames_dropped <= r.frames_received


class TestDisplays:
    def test_late_and_slow_displays_never_stall_the_pipeline(self, make_server):
        server = make_server(process=identity_step())
        address = server.connect_address
        deaf = RawPeer(address, rcvhwm=1, rcvbuf=4096)  # subscribes, then never reads
        assert isinstance(deaf.hello("shared", role="display"), Welcome)
        deaf_alive = deaf.keep_alive()  # heartbeats only: the server must not think it dead
        slow = DisplayClient(
            DisplayOptions(server=address, session="shared", idle_exit_s=3.0), read_delay_s=0.02
        )
        late = DisplayClient(DisplayOptions(server=address, session="shared", idle_exit_s=3.0))
        threads = {
            "slow": threading.Thread(target=slow.run, daemon=True),
            "late": threading.Thread(target=late.run, daemon=True),
        }
        threads["slow"].start()
        assert slow.subscribed.wait(10)
        late_seqs: list[int] = []
        late.on_result = lambda r, _: late_seqs.append(r.seq)

        def on_result(result, _):
            if result.seq == 100:
                threads["late"].start()

        n = 300
        options = StreamOptions(
            server=address,
            session="shared",
            mode="lossless",
            rate="max",
            color_codec="raw",
            depth_codec="raw",
            want_composite=True,
        )
        summary = run_with_timeout(
            lambda: stream(flat_source(n, 320, 240, noise=True), options, on_result=on_result)
        )
        assert summary.results == n and summary.errors == []
        for thread in threads.values():
            thread.join(30)
            assert not thread.is_alive()
        assert late_seqs and late_seqs[0] > 0  # it joined late: no history is replayed
        assert late_seqs == sorted(late_seqs)
        assert 0 < slow.summary.results <= n
        # the deaf display's queue filled up: the server dropped Results for it alone
        assert server.stats.display_results_dropped > 0
        deaf_alive.set()
        deaf.close()


class TestLiveness:
    def test_idle_session_expires_and_silent_peer_is_dead(self, make_server):
        server = make_server(process=identity_step(), session_timeout_s=1.5)
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("idle"), Welcome)
        peer.send(_frame_parts(seq=0))
        assert isinstance(peer.receive(), Result)
        # the peer now stays silent (no heartbeats): dead after 3 intervals (0.6 s); the
        # session expires after its timeout (1.5 s without frames) and frees its state
        wait_for(lambda: "idle" not in server.snapshot()["sessions"], 10)
        snapshot = server.snapshot()
        assert snapshot["sessions_expired"] == 1 and snapshot["peers_expired"] >= 1
        peer.send(_frame_parts(seq=1))
        error = peer.receive()
        assert isinstance(error, Error) and error.code == "bad_state"
        assert error.field == "session" and error.seq == 1
        peer.close()

    def test_killed_capture_client_leaves_the_server_serving_others(self, make_server, tmp_path):
        server = make_server(process=identity_step())
        script = tmp_path / "victim.py"
        script.write_text(
            "import sys\n"
            f"sys.path.insert(0, {os.path.dirname(__file__)!r})\n"
            "from streaming_support import flat_source\n"
            "from arlight.client.capture import StreamOptions, stream\n"
            f"stream(flat_source(100000), StreamOptions(server={server.connect_address!r}, "
            "session='victim', mode='live', rate='native'))\n"
        )
        victim = subprocess.Popen(
            [sys.executable, str(script)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        try:
            wait_for(
                lambda: (
                    server.snapshot()["sessions"].get("victim", {}).get("frames_received", 0) >= 5
                ),
                60,
                what="the victim's frames",
            )
        finally:
            victim.kill()
            victim.wait(10)
        survivor = StreamOptions(
            server=server.connect_address, session="survivor", mode="lossless", rate="max"
        )
        summary = run_with_timeout(lambda: stream(flat_source(5), survivor))
        assert summary.results == 5 and summary.errors == []
        wait_for(
            lambda: not server.snapshot()["sessions"]["victim"]["capture_attached"],
            10,
            what="the dead capture peer to be detached",
        )

    def test_capture_client_survives_a_server_restart_without_losing_frames(self, make_server):
        server = make_server(process=identity_step(delay_s=0.02))
        port = server.port
        seqs: list[int] = []
        client = CaptureClient(
            flat_source(60),
            StreamOptions(
                server=f"tcp://127.0.0.1:{port}",
                session="phoenix",
                mode="lossless",
                rate="max",
                reconnect_timeout_s=20.0,
            ),
            on_result=lambda r, _: seqs.append(r.seq),
        )
        runner = CaptureClientThread(client)
        runner.start()
        wait_for(lambda: len(seqs) >= 15, 30, what="15 results before the restart")
        server.stop()
        time.sleep(0.3)  # the client notices (Bye) and retries while the port is closed
        second = make_server(process=identity_step(delay_s=0.02), bind=f"tcp://127.0.0.1:{port}")
        summary = runner.join()
        assert summary.reconnects >= 1
        assert seqs == list(range(60))  # every frame exactly once, in order
        assert summary.errors == []
        assert (
            "phoenix" in second.snapshot()["sessions"] or second.stats.sessions_closed >= 1
        )  # it said Hello again to the new server

    def test_shutdown_finishes_or_reports_in_flight_lossless_frames(self, make_server):
        server = make_server(
            process=identity_step(delay_s=0.4), shutdown_grace_s=1.0, heartbeat_interval_s=5.0
        )  # the raw peer sends no heartbeats
        peer = RawPeer(server.connect_address)
        welcome = peer.hello("drain")
        assert welcome.credits >= 4
        for seq in range(4):
            peer.send(_frame_parts(seq=seq))
        time.sleep(0.1)
        stopper = threading.Thread(target=server.stop)
        stopper.start()
        outcome: dict[int, str] = {}
        while True:
            message = peer.receive(15)
            if isinstance(message, Bye):
                break
            assert message.seq not in outcome
            if isinstance(message, Result):
                outcome[message.seq] = "processed"
            else:
                assert message.code == "bad_state" and message.field == "shutdown"
                outcome[message.seq] = "reported"
        stopper.join(15)
        assert sorted(outcome) == [0, 1, 2, 3]
        assert "processed" in outcome.values() and "reported" in outcome.values()
        peer.close()

    def test_serve_command_shuts_down_cleanly_on_sigterm(self):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "arlight.cli",
                "serve",
                "--bind",
                f"tcp://127.0.0.1:{port}",
                "--heartbeat",
                "0.2",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            peer = RawPeer(f"tcp://127.0.0.1:{port}")
            welcome = peer.hello("cli", timeout_s=60)  # includes the interpreter's start-up
            assert isinstance(welcome, Welcome)
            proc.send_signal(signal.SIGTERM)
            assert isinstance(peer.receive(15), Bye)
            _, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, stderr
        assert "SIGTERM" in stderr and "server stopped" in stderr
        peer.close()


# --------------------------------------------------------------------------- hostile input


def _frame_parts(
    seq: int = 0,
    width: int = 64,
    height: int = 48,
    value: int = 7,
    color_codec: str = "raw",
    depth_codec: str = "raw",
) -> list[bytes]:
    frame = Frame(
        seq,
        1.0,
        np.full((height, width, 3), value, np.uint8),
        np.full((height, width), 7500, np.uint16),
        None,
        None,
        color_codec,
        depth_codec,
    )
    return [bytes(memoryview(p)) for p in encode(frame)]


def _edit(parts: list[bytes], edit) -> list[bytes]:
    header = msgpack.unpackb(parts[0])
    edit(header)
    return [msgpack.packb(header, use_bin_type=True), *parts[1:]]


def _set_sizes(header, w, h):
    for key in ("color", "depth"):
        header[key]["width"], header[key]["height"] = w, h


def _hello_parts(**config) -> list:
    base = dict(session="hostile", role="capture", calibration=None)
    base.update(config)
    return encode(Hello(PROTOCOL_VERSION, SessionConfig(**base)))


def _corrupt_jpeg() -> list[bytes]:
    """A frame whose JPEG payload is not a JPEG (its declared length is right)."""
    parts = _frame_parts(color_codec="jpeg")
    junk = b"\xff\xd8" + b"\x13" * 200
    parts = _edit(parts, lambda h: h["buffers"].__setitem__(0, len(junk)))
    return [parts[0], junk, parts[2]]


def _calibrated(**config):
    from arlight.pipeline.camera import PinholeCamera
    from arlight.sources.source import calibration_of

    return dict(calibration=calibration_of(PinholeCamera.kinect_v1(64, 48)), **config)


def _pose_nan(header):
    header["pose"] = [[math.nan, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def _bad_depth_codec(header):
    header["depth"]["format"] = "lz4"


def _declare_huge_buffer(header):
    header["buffers"][0] = 2**40


# (name, needs a session first, parts, expected code, expected field prefix or None)
HOSTILE = [
    ("garbage bytes", False, [b"\x00\xffnot msgpack at all"], "malformed", None),
    ("empty part", False, [b""], "malformed", None),
    ("header not a map", False, [msgpack.packb([1, 2, 3])], "malformed", None),
    (
        "unknown version",
        False,
        [msgpack.packb({"v": 99, "type": "hello", "config": {}})],
        "bad_version",
        "v",
    ),
    (
        "unknown type",
        False,
        [msgpack.packb({"v": PROTOCOL_VERSION, "type": "teleport"})],
        "unknown_type",
        "type",
    ),
    ("frame before hello", False, _frame_parts(), "bad_state", "session"),
    ("hello without calibration", False, None, "bad_field", "hello.config.calibration"),
    ("unknown preset", False, None, "bad_field", "hello.config.preset"),
    ("unknown override", False, None, "bad_field", "hello.config.overrides"),
    ("wrong override type", False, None, "bad_field", "hello.config.overrides"),
    ("engine layouts with 2 SH bands", False, None, "bad_field", "hello.config.exports"),
    ("a client sending a Result", False, None, "bad_state", "type"),
    (
        "huge declared image",
        True,
        _edit(_frame_parts(), lambda h: _set_sizes(h, 60000, 60000)),
        "too_large",
        "frame.color",
    ),
    (
        "huge declared buffer",
        True,
        _edit(_frame_parts(), _declare_huge_buffer),
        "malformed",
        "frame.buffers",
    ),
    ("truncated multipart", True, _frame_parts()[:-1], "malformed", "frame.buffers"),
    ("NaN pose", True, _edit(_frame_parts(), _pose_nan), "bad_field", "frame.pose"),
    (
        "colour and depth sizes differ",
        True,
        _edit(_frame_parts(), lambda h: h["depth"].update(width=32)),
        "bad_field",
        "frame",
    ),
    (
        "frame size differs from the calibration",
        True,
        _frame_parts(width=32, height=24),
        "bad_field",
        "frame.color",
    ),
    ("undecodable JPEG", True, _corrupt_jpeg(), "decode_failed", "frame.color"),
    (
        "unknown depth codec",
        True,
        _edit(_frame_parts(), _bad_depth_codec),
        "bad_codec",
        "frame.depth",
    ),
    (
        "negative seq",
        True,
        _edit(_frame_parts(), lambda h: h.update(seq=-1)),
        "bad_field",
        "frame.seq",
    ),
]


def _hello_case(name: str) -> list:
    if name == "hello without calibration":  # encode() refuses it: edit the header by hand
        parts = [bytes(memoryview(p)) for p in _hello_parts(**_calibrated())]
        return _edit(parts, lambda h: h["config"].update(calibration=None))
    if name == "unknown preset":
        return _hello_parts(**_calibrated(preset="ultra"))
    if name == "unknown override":
        return _hello_parts(**_calibrated(overrides={"no_such_field": 1}))
    if name == "wrong override type":
        return _hello_parts(**_calibrated(overrides={"sh_bands": "many"}))
    if name == "engine layouts with 2 SH bands":
        return _hello_parts(**_calibrated(overrides={"sh_bands": 2}, exports=("arcore",)))
    if name == "a client sending a Result":
        return encode(
            Result(
                seq=0,
                timestamp=1.0,
                sh=[0.0],
                dominant_direction_camera=[0, 0, 1],
                dominant_direction_world=[0, 0, 1],
                intensity=0.0,
                confidence={},
                pose=np.eye(4).tolist(),
                timings_ms={},
                frames_received=0,
                frames_processed=0,
                frames_dropped=0,
                server_receive_time=0.0,
                server_finish_time=0.0,
            )
        )
    raise KeyError(name)


@pytest.fixture(scope="module")
def hostile_server():
    """One server for every hostile message, with a bystander session that must not notice."""
    server = Server(
        ServerOptions(
            bind="tcp://127.0.0.1:*",
            heartbeat_interval_s=1.0,
            log_interval_s=60.0,
            max_message_bytes=2**20,
        ),
        process=identity_step(),
    ).start()
    bystander = RawPeer(server.connect_address)
    assert isinstance(bystander.hello("bystander"), Welcome)
    bystander.send(_frame_parts(seq=0, value=11))
    assert isinstance(bystander.receive(), Result)
    yield server, bystander
    bystander.close()
    server.stop(timeout=15)


class TestHostileInput:
    @pytest.mark.parametrize(
        "name, needs_session, parts, code, field", HOSTILE, ids=[case[0] for case in HOSTILE]
    )
    def test_gets_an_error_reply(self, hostile_server, name, needs_session, parts, code, field):
        server, _ = hostile_server
        peer = RawPeer(server.connect_address)
        try:
            if needs_session:
                assert isinstance(peer.hello(f"h{abs(hash(name)) % 10**6}"), Welcome)
            peer.send(parts if parts is not None else _hello_case(name))
            error = peer.receive()
            assert isinstance(error, Error), error
            assert error.code == code, error
            if field is not None:
                assert (error.field or "").startswith(field), error
            if needs_session and name != "negative seq":
                assert error.seq == 0  # the Error names the frame (lossless: acknowledges it)
        finally:
            peer.close()

    def test_oversized_message_drops_only_that_connection(self, hostile_server):
        server, _ = hostile_server
        peer = RawPeer(server.connect_address)
        peer.send([b"\x00" * (2 * 2**20)])  # over MAXMSGSIZE: zmq closes that connection
        assert not peer.socket.poll(500)
        peer.close()
        other = RawPeer(server.connect_address)
        assert isinstance(other.hello("after-oversized"), Welcome)
        other.close()

    def test_bystander_session_untouched_and_server_serving(self, hostile_server):
        server, bystander = hostile_server
        bystander.send(_frame_parts(seq=1, value=12))
        result = bystander.receive()
        assert isinstance(result, Result) and result.seq == 1
        assert result.sh[0] == pytest.approx(12.0)
        assert result.frames_received == result.frames_processed == 2
        assert result.frames_dropped == 0
        assert server.snapshot()["sessions"]["bystander"]["frames_failed"] == 0
        fresh = StreamOptions(
            server=server.connect_address, session="fresh", mode="lossless", rate="max"
        )
        summary = run_with_timeout(lambda: stream(flat_source(3), fresh))
        assert summary.results == 3 and summary.errors == []


# --------------------------------------------------------------------------- typed protocol


class TestTypedMeaning:
    """What a client acts on is typed in the message: Error.retryable, Bye.kind (v2)."""

    def test_retryable_errors_are_flagged_and_final_ones_not(self, make_server):
        server = make_server(
            process=identity_step(delay_s=0.1), credits=1, heartbeat_interval_s=5.0
        )
        stranger = RawPeer(server.connect_address)
        stranger.send(_frame_parts(seq=0))
        error = stranger.receive()
        assert (error.code, error.field, error.seq, error.retryable) == (
            "bad_state",
            "session",
            0,
            True,
        )
        stranger.close()
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("typed"), Welcome)
        for seq in range(6):  # credits 1: the queue holds 3, the rest is refused
            peer.send(_frame_parts(seq=seq))
        answers = [peer.receive(15) for _ in range(6)]
        refused = [m for m in answers if isinstance(m, Error)]
        assert refused and all(m.field == "credits" and m.retryable for m in refused)
        peer.close()
        fresh = RawPeer(server.connect_address)
        assert isinstance(fresh.hello("typed-final"), Welcome)
        fresh.send(_frame_parts(seq=0, width=32, height=24))  # final: not the calibration
        error = fresh.receive(15)
        assert error.seq == 0 and error.code == "bad_field" and error.retryable is False
        fresh.close()

    def test_diagnostics_reach_capture_and_display_clients(self, make_server):
        step = identity_step()

        def with_diagnostics(frame, session, render_light, deadline):
            result = step(frame, session, render_light, deadline)
            result.diagnostics = {
                "tracking": {"ok": True, "reason": ""},
                "residuals": np.array([0.5, 0.25]),
                "n": np.int64(3),
            }
            return result

        server = make_server(process=with_diagnostics)
        display = DisplayClient(
            DisplayOptions(server=server.connect_address, session="diag", idle_exit_s=30.0)
        )
        thread = threading.Thread(target=display.run, daemon=True)
        shown: list[Result] = []
        display.on_result = lambda r, _: shown.append(r)
        thread.start()
        assert display.subscribed.wait(10)
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address, session="diag", mode="lossless", rate="max"
        )
        run_with_timeout(
            lambda: stream(flat_source(2), options, on_result=lambda r, _: results.append(r))
        )
        thread.join(30)
        expected = {"tracking": {"ok": True, "reason": ""}, "residuals": [0.5, 0.25], "n": 3}
        assert [r.diagnostics for r in results] == [expected, expected]
        assert results[0].sh_camera == results[0].sh
        assert display.summary.ended and [r.diagnostics for r in shown] == [expected] * 2

    def test_non_plain_diagnostics_fail_the_frame_with_a_clear_error(self, make_server):
        step = identity_step()

        def bad(frame, session, render_light, deadline):
            result = step(frame, session, render_light, deadline)
            result.diagnostics = {"mesh": object()}
            return result

        server = make_server(process=bad, heartbeat_interval_s=5.0)
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("bad-diag"), Welcome)
        peer.send(_frame_parts(seq=0))
        error = peer.receive(15)
        assert error.code == "internal" and error.seq == 0 and not error.retryable
        assert "result.diagnostics.mesh" in error.message
        peer.close()

    def test_end_of_stream_and_shutdown_byes_have_their_kinds(self, make_server):
        server = make_server(process=identity_step(), heartbeat_interval_s=5.0)
        display = RawPeer(server.connect_address)
        assert isinstance(display.hello("kinds", role="display"), Welcome)
        capture = RawPeer(server.connect_address)
        assert isinstance(capture.hello("kinds"), Welcome)
        capture.send(_frame_parts(seq=0))
        assert isinstance(capture.receive(15), Result)
        capture.send_message(Bye("end of stream", ByeKind.END_OF_STREAM))
        assert isinstance(display.receive(15), Result)
        bye = display.receive(15)
        assert isinstance(bye, Bye) and bye.kind is ByeKind.END_OF_STREAM
        server.stop(timeout=15)
        bye = display.receive(15)
        assert isinstance(bye, Bye) and bye.kind is ByeKind.SHUTDOWN
        display.close()
        capture.close()


# --------------------------------------------------------------------------- virtual scene


def _scene_object(name: str = "tri", **kw) -> SceneObjectSpec:
    args = dict(
        vertices=np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32),
        triangles=np.array([[0, 1, 2]], np.uint32),
        normals=np.array([[0, 0, -1]] * 3, np.float32),
        world_from_object=np.eye(4),
    )
    args.update(kw)
    return SceneObjectSpec(name, **args)


def _scene_hello(scene: SceneSpec | None = None, session: str = "scene", **config) -> list:
    return [
        bytes(memoryview(p))
        for p in _hello_parts(
            **_calibrated(
                session=session,
                scene=SceneSpec((_scene_object(),)) if scene is None else scene,
                **config,
            )
        )
    ]


def _replace_part(parts: list[bytes], i: int, data: bytes) -> list[bytes]:
    parts = [*parts[:i], data, *parts[i + 1 :]]
    return _edit(parts, lambda h: h.update(buffers=[len(p) for p in parts[1:]]))


def _object_edit(**fields):
    return lambda h: h["config"]["scene"]["objects"][0].update(**fields)


def _assert_same_object(got, sent, vertices=None) -> None:
    """A pipeline VirtualObject made by the server equals the client's, bit for bit."""
    assert got.name == sent.name and got.material == sent.material
    assert got.anchor == sent.anchor
    want = sent.vertices if vertices is None else vertices
    np.testing.assert_array_equal(got.vertices.view(np.uint32), want.view(np.uint32))
    np.testing.assert_array_equal(got.normals.view(np.uint32), sent.normals.view(np.uint32))
    np.testing.assert_array_equal(got.triangles, sent.triangles)


# (name, Hello parts, expected field prefix)
BAD_SCENES = [
    (
        "vertices part one vertex short",
        _replace_part(_scene_hello(), 1, _scene_hello()[1][:-12]),
        "hello.config.scene.vertices",
    ),
    (
        "triangles part not whole triangles",
        _replace_part(_scene_hello(), 2, _scene_hello()[2] + b"\0\0"),
        "hello.config.scene.triangles",
    ),
    (
        "too many triangles",
        _edit(_scene_hello(), _object_edit(triangle_count=2_000_001)),
        "hello.config.scene.objects[0].triangle_count",
    ),
    (
        "triangle index out of range",
        _replace_part(_scene_hello(), 2, np.array([[0, 1, 3]], "<u4").tobytes()),
        "hello.config.scene.objects[0].triangles",
    ),
    (
        "NaN pose",
        _edit(_scene_hello(), _object_edit(world_from_object=[math.nan] * 16)),
        "hello.config.scene.objects[0].world_from_object",
    ),
    (
        "pose and anchor",
        _edit(_scene_hello(), _object_edit(anchor={"pixel": [32.0, 24.0], "yaw_deg": 0.0})),
        "hello.config.scene.objects[0].anchor",
    ),
    (
        "sheared pose (the pipeline's own check)",
        _scene_hello(
            SceneSpec(
                (
                    _scene_object(
                        "sheared",
                        world_from_object=np.array(
                            [[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]
                        ),
                    ),
                )
            )
        ),
        "hello.config.scene.objects[0]",
    ),
    (
        "scene and virtual_scene",
        _edit(_scene_hello(), lambda h: h["config"].update(virtual_scene="demo")),
        "hello.config.scene",
    ),
    (
        "unknown scene name",
        [
            bytes(memoryview(p))
            for p in _hello_parts(**_calibrated(session="scene", virtual_scene="bunny.ply"))
        ],
        "hello.config.virtual_scene",
    ),
]


class TestVirtualScene:
    def test_the_sessions_pipeline_gets_the_scene_sent(self, make_server):
        """A VirtualScene in StreamOptions reaches the session's Pipeline bit for bit (an
        anchored object's scale applied to its vertices), and the real pipeline's Results
        arrive."""
        from arlight.pipeline.virtual_scene import (
            Anchor,
            Material,
            VirtualScene,
            box_mesh,
            object_from_open3d,
            sphere_mesh,
        )

        placed = object_from_open3d(
            "ball",
            sphere_mesh(0.05, 8),
            np.array([[0, 0, 1, 0.1], [0, 1, 0, 0.2], [-1, 0, 0, 1.5], [0, 0, 0, 1.0]]),
            Material((0.2, 0.4, 0.6), 0.5, 0.25, True),
        )
        anchored = object_from_open3d(
            "crate",
            box_mesh((0.1, 0.1, 0.1)),
            np.diag([2.0, 2.0, 2.0, 1.0]),
            Material(),
            Anchor((80.0, 90.0), 30.0),
        )
        scene = VirtualScene((placed, anchored))
        server = make_server()
        seq = make_sequence(num_frames=2, width=160, height=120, seed=1)
        source = sequence_source("scene", seq.camera, seq.frames)
        seen = []

        def on_result(result, _):
            seen.append((result, server.sessions["scene"].compute.pipeline.requested_scene))

        options = StreamOptions(
            server=server.connect_address,
            session="scene",
            mode="lossless",
            rate="max",
            preset="fast",
            overrides=SMALL,
            scene=scene,
        )
        summary = run_with_timeout(lambda: stream(source, options, on_result=on_result))
        assert summary.errors == [] and [r.seq for r, _ in seen] == [0, 1]
        got = seen[0][1]
        assert isinstance(got, VirtualScene) and [o.name for o in got.objects] == ["ball", "crate"]
        _assert_same_object(got.objects[0], placed)
        np.testing.assert_array_equal(got.objects[0].world_from_object, placed.world_from_object)
        _assert_same_object(
            got.objects[1], anchored, vertices=(anchored.vertices * 2.0).astype(np.float32)
        )
        np.testing.assert_array_equal(got.objects[1].world_from_object, np.eye(4))

    def test_demo_scene_by_name_and_none_without(self, make_server):
        from arlight.pipeline.virtual_scene import demo_scene

        server = make_server(process=identity_step())
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("demo-scene", virtual_scene="demo"), Welcome)
        scene = server.sessions["demo-scene"].scene
        assert [o.name for o in scene.objects] == [o.name for o in demo_scene().objects]
        plain = RawPeer(server.connect_address)
        assert isinstance(plain.hello("no-scene"), Welcome)
        assert server.sessions["no-scene"].scene is None
        peer.close()
        plain.close()

    def test_a_reconnect_with_the_same_scene_resumes_the_session(self, make_server):
        server = make_server(process=identity_step())
        first, again, other = (RawPeer(server.connect_address) for _ in range(3))
        first.send(_scene_hello())
        assert isinstance(first.receive(), Welcome)
        session = server.sessions["scene"]
        again.send(_scene_hello())  # equal arrays, other buffers: the same configuration
        assert isinstance(again.receive(), Welcome)
        assert server.sessions["scene"] is session
        moved = SceneSpec(
            (_scene_object(world_from_object=np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3)),)
        )
        other.send(_scene_hello(moved))
        error = other.receive()
        assert (error.code, error.field) == ("bad_state", "hello.config.session")
        for peer in (first, again, other):
            peer.close()

    def test_bad_scenes_are_refused_and_the_server_keeps_serving(self, make_server):
        server = make_server(process=identity_step())
        bystander = RawPeer(server.connect_address)
        assert isinstance(bystander.hello("bystander"), Welcome)
        for seq, (name, parts, field) in enumerate(BAD_SCENES):
            peer = RawPeer(server.connect_address)
            peer.send(parts)
            error = peer.receive()
            assert isinstance(error, Error), (name, error)
            assert error.code == "bad_field" and not error.retryable, (name, error)
            assert (error.field or "").startswith(field), (name, error)
            assert "scene" not in server.sessions, name  # no session was created
            if name.startswith("sheared"):
                assert "'sheared'" in error.message  # names the object
            if name == "unknown scene name":
                assert "arlight stream --scene FILE" in error.message
            peer.close()
            bystander.send(_frame_parts(seq=seq, value=seq))
            result = bystander.receive()
            assert isinstance(result, Result) and result.seq == seq
        bystander.close()
        # the refusal reaches a capture client as a clear, final StreamError
        options = StreamOptions(
            server=server.connect_address, session="named", virtual_scene="bunny.ply"
        )
        with pytest.raises(StreamError, match="unknown virtual scene name 'bunny.ply'"):
            run_with_timeout(lambda: stream(flat_source(1), options))

    @pytest.mark.parametrize("codec", ["raw", "png"])
    def test_no_scene_composite_is_the_input_bit_for_bit(self, make_server, codec):
        server = make_server(process=identity_step())
        source = flat_source(3, 64, 48, noise=True)
        display = RawPeer(server.connect_address)
        assert isinstance(display.hello("composite", role="display"), Welcome)
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address,
            session="composite",
            mode="lossless",
            rate="max",
            color_codec=codec,
            want_composite=True,
        )
        summary = run_with_timeout(
            lambda: stream(source, options, on_result=lambda r, _: results.append(r))
        )
        assert summary.errors == [] and len(results) == 3
        shown = [display.receive() for _ in range(3)]
        for got, also, frame in zip(results, shown, source.frames(), strict=True):
            assert got.composite_codec == codec  # as the colour came: lossless stays lossless
            assert got.composite.dtype == np.uint8
            np.testing.assert_array_equal(got.composite, frame.color)
            np.testing.assert_array_equal(also.composite, frame.color)
        display.close()

    def test_with_a_scene_the_composite_is_the_pipelines(self, make_server):
        """The pipeline's composite when it makes one; the input frame while it makes none."""
        identity = identity_step()

        def rendering(frame, session, render_light, deadline):
            out = identity(frame, session, render_light, deadline)
            return (
                dataclasses.replace(out, composite=255 - frame.color)
                if frame.timestamp > 1000.02
                else out
            )  # none for the first frame

        server = make_server(process=rendering)
        results: list[Result] = []
        source = flat_source(2, 64, 48, noise=True)
        options = StreamOptions(
            server=server.connect_address,
            session="rendered",
            mode="lossless",
            rate="max",
            color_codec="png",
            want_composite=True,
            scene=_virtual_scene(),
        )
        summary = run_with_timeout(
            lambda: stream(source, options, on_result=lambda r, _: results.append(r))
        )
        assert summary.errors == []
        first, second = (frame.color for frame in source.frames())
        np.testing.assert_array_equal(results[0].composite, first)
        np.testing.assert_array_equal(results[1].composite, 255 - second)
        # the same step without a scene: the input frame, whatever the pipeline made
        results.clear()
        options = dataclasses.replace(options, session="unrendered", scene=None)
        run_with_timeout(lambda: stream(source, options, on_result=lambda r, _: results.append(r)))
        np.testing.assert_array_equal(results[1].composite, second)


def test_a_hello_that_cannot_be_sent_is_a_stream_error():
    """Refused by encode() before any socket opens: scene and virtual_scene together."""
    options = StreamOptions(
        server="tcp://127.0.0.1:9",
        session="unsendable",
        virtual_scene="demo",
        scene=_virtual_scene(),
    )
    with pytest.raises(StreamError, match=r"cannot be sent: bad_field \(hello.config.scene\)"):
        run_with_timeout(lambda: stream(flat_source(1), options), timeout_s=10)


def _virtual_scene():
    from arlight.pipeline.virtual_scene import VirtualObject, VirtualScene

    spec = _scene_object()
    return VirtualScene(
        (
            VirtualObject(
                spec.name,
                spec.vertices,
                spec.triangles.astype(np.int32),
                spec.normals,
                spec.world_from_object,
            ),
        )
    )
