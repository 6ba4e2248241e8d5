"""The streaming server over real loopback sockets (issue 3, item 5): lossless delivery,
duplicates, credit and resumed sessions. Live sessions, displays and liveness:
test_server_sessions.py; hostile input: test_server_hostile.py; the virtual scene:
test_server_scene.py."""

from __future__ import annotations

import collections
import logging
import threading

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
    wait_for,
)
from streaming_support import frame_parts as _frame_parts

from arlight.client.capture import CaptureClient, StreamOptions, stream
from arlight.core.frames import FrameInput
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import FrameError, Pipeline
from arlight.protocols import PROTOCOL_VERSION, Error, Frame, Hello, Result, Welcome, decode, encode
from arlight.sources.source import open_source, sequence_source
from arlight.sources.synthetic import make_sequence


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
    from arlight.core.camera import PinholeCamera

    c = source.calibration
    return PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy)
