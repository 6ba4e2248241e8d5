"""The streaming server over real loopback sockets, given hostile input: each bad message
gets its typed error and the server keeps serving the other sessions; errors, diagnostics
and byes mean what they say (issue 3, item 5)."""

from __future__ import annotations

import math
import threading

import msgpack
import numpy as np
import pytest
from streaming_support import RawPeer, flat_source, identity_step, run_with_timeout
from streaming_support import calibrated as _calibrated
from streaming_support import edit_header as _edit
from streaming_support import frame_parts as _frame_parts
from streaming_support import hello_parts as _hello_parts

from arlight.client.capture import StreamOptions, stream
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.protocols import PROTOCOL_VERSION, Bye, ByeKind, Error, Result, Welcome, encode
from arlight.server.server import Server, ServerOptions

# --------------------------------------------------------------------------- hostile input


def _set_sizes(header, w, h):
    for key in ("color", "depth"):
        header[key]["width"], header[key]["height"] = w, h


def _corrupt_jpeg() -> list[bytes]:
    """A frame whose JPEG payload is not a JPEG (its declared length is right)."""
    parts = _frame_parts(color_codec="jpeg")
    junk = b"\xff\xd8" + b"\x13" * 200
    parts = _edit(parts, lambda h: h["buffers"].__setitem__(0, len(junk)))
    return [parts[0], junk, parts[2]]


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
