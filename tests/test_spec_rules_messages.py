"""SPEC.md read as an outside implementer reads it (issue 36), points 2 to 7: directions
without an estimate, result_panorama.bin, the seq bound, the version rule, the ambiguities
settled, repeated keys; each checked against the golden vectors, the decoder and a loopback
server. Points 1, 8 and 9: test_spec_rules.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import expect_refusal as expect
from conftest import golden_bytes as golden_parts
from conftest import load_vector_script, refused_parts, spec_section
from streaming_support import SMALL, RawPeer, identity_step

from arlight.pipeline.runtime import configure_open3d_threads
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    Error,
    Frame,
    Heartbeat,
    Hello,
    Result,
    SessionConfig,
    Welcome,
    decode,
    encode,
)

# one Open3D thread: tracking is deterministic (SPEC.md section 11, as the entry points set)
configure_open3d_threads(1)


VEC = load_vector_script("make_protocol_vectors_rules")


# --------------------------------------------------------------------------- 2. directions


def _result(**changes) -> Result:
    fields = dict(
        seq=1,
        timestamp=1.0,
        sh=[1.0, 0.0, 0.0, 0.0],
        sh_camera=None,
        dominant_direction_camera=[0.0, 0.0, 1.0],
        dominant_direction_world=[0.0, 0.0, 1.0],
        intensity=1.0,
        confidence={},
        pose=np.eye(4).tolist(),
        timings_ms={},
        frames_received=1,
        frames_processed=1,
        frames_dropped=0,
        server_receive_time=1.0,
        server_finish_time=1.0,
    )
    fields.update(changes)
    return Result(**fields)


def _with_header(message, **values) -> list[bytes]:
    """The parts of `message` with header keys replaced (bytes the encoder would refuse)."""

    def edit(header):
        header.update(values)
        return header

    return VEC.edited(message, edit)


class TestDirections:
    """Point 2: a direction is a unit vector or exactly [0, 0, 0], "no direction"; the server
    sends the zero vector (with intensity 0) while its estimate has none."""

    def test_the_no_direction_vector(self):
        result = decode(golden_parts("result_no_direction"))
        assert result.dominant_direction_camera == result.dominant_direction_world == [0.0] * 3
        assert result.intensity == 0.0
        assert result.confidence.value == 0.0 and result.confidence.reason == "no valid depth"

    @pytest.mark.parametrize(
        "direction", [[0.0, 0.0, 1.0], [0.0, 0.0, 1.009], [0.0, 0.0, 0.0], [0.6, 0.0, -0.8]]
    )
    def test_unit_or_zero_is_accepted(self, direction):
        parts = _with_header(
            _result(), dominant_direction_camera=direction, dominant_direction_world=direction
        )
        assert decode(parts).dominant_direction_world == direction

    @pytest.mark.parametrize(
        "direction", [[0.0, 0.0, 1.02], [0.0, 0.0, 0.5], [1.0, 1.0, 0.0], [0.0, 0.0, -0.98]]
    )
    def test_anything_else_is_refused(self, direction):
        parts = _with_header(_result(), dominant_direction_world=direction)
        expect("bad_field", "result.dominant_direction_world", decode, parts)
        expect(
            "bad_field",
            "result.dominant_direction_world",
            encode,
            _result(dominant_direction_world=direction),
        )

    def test_zero_in_one_frame_only_is_refused(self):
        parts = _with_header(_result(), dominant_direction_world=[0.0, 0.0, 0.0])
        expect("bad_field", "result.dominant_direction_camera", decode, parts)

    def test_panorama_direction_follows_the_same_rule(self):
        pano = dict(panorama_sh=[1.0, 0, 0, 0], panorama_sh_rgb=[[1.0, 0, 0, 0]] * 3)
        assert decode(encode(_result(**pano, panorama_dominant_direction=[0.0, 0.0, 0.0])))
        expect(
            "bad_field",
            "result.panorama_dominant_direction",
            encode,
            _result(**pano, panorama_dominant_direction=[0.0, 2.0, 0.0]),
        )

    def test_server_sends_zero_without_an_estimate(self, make_server):
        """A session's first frame without usable depth: the real pipeline has no estimate;
        the Result says so with [0, 0, 0] in both frames and intensity 0."""
        server = make_server()
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("nodir", preset="fast", overrides=SMALL), Welcome)
        color = np.full((48, 64, 3), 128, np.uint8)
        peer.send_message(
            Frame(0, 10.0, color, np.zeros((48, 64), np.uint16), None, None, "png", "zstd")
        )
        result = peer.receive(timeout_s=60)
        while result is not None and not isinstance(result, (Result, Error)):
            result = peer.receive(timeout_s=60)  # a Credit may come first
        assert isinstance(result, Result), result
        assert result.dominant_direction_world == result.dominant_direction_camera == [0.0] * 3
        assert result.intensity == 0.0
        assert result.confidence.reason == "no valid depth"
        peer.close()


# --------------------------------------------------------------------------- 3. panorama


def _sloan_intensity(coeffs: list[float], direction: list[float]) -> float:
    from arlight.pipeline.sh import intensity_along

    return intensity_along(np.array(coeffs), np.array(direction))


def _normalized_band1(c: list[float]) -> list[float]:
    v = np.array([c[3], c[1], c[2]])
    return (v / np.linalg.norm(v)).tolist()


class TestPanoramaVector:
    """Point 3: result_panorama.bin is the Result of frame_panorama_only.bin in the session
    of hello_panorama_only.bin, every part as SPEC.md section 4 defines it."""

    def test_every_part_is_what_the_spec_defines(self):
        result = decode(golden_parts("result_panorama"))
        frame = decode(golden_parts("frame_panorama_only"))
        hello = decode(golden_parts("hello_panorama_only"))
        identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        assert hello.config.panorama.panorama_from_world == identity
        assert (result.seq, result.timestamp) == (frame.seq, frame.timestamp)
        rgb = np.array(result.panorama_sh_rgb)
        np.testing.assert_allclose(result.panorama_sh, [0.2126, 0.7152, 0.0722] @ rgb, rtol=1e-12)
        np.testing.assert_allclose(
            result.panorama_dominant_direction, _normalized_band1(result.panorama_sh), rtol=1e-12
        )
        np.testing.assert_allclose(
            result.panorama_dominant_direction, [0.535, 0.618, 0.576], atol=1e-3
        )  # the figure SPEC.md section 9 quotes
        assert result.sh == result.sh_camera == result.panorama_sh
        assert result.sh_rgb == result.panorama_sh_rgb
        assert (
            result.dominant_direction_world
            == result.dominant_direction_camera
            == result.panorama_dominant_direction
        )
        assert result.intensity == pytest.approx(
            _sloan_intensity(result.sh, result.dominant_direction_world), abs=1e-9
        )
        assert result.pose == np.eye(4).tolist() and result.composite is None
        conf = result.confidence
        assert (
            conf.samples,
            conf.condition_number,
            conf.bands_estimated,
            conf.value,
            conf.reason,
        ) == (128, 1.0, 4, 1.0, "")
        assert result.diagnostics == {"light_source": "panorama", "panorama_operator": "boost"}
        assert set(result.timings_ms) == {
            "PanoramaInverseTone",
            "PanoramaDownsample",
            "PanoramaSH",
            "PanoramaDiffuse",
        }

    def test_the_server_sends_what_the_spec_defines(self, make_server):
        """A panorama-only session with the identity rotation: the same relations hold for
        the server's own Result of a real panorama."""
        from arlight.protocols import PanoramaConfig

        server = make_server()
        peer = RawPeer(server.connect_address)
        peer.send_message(
            Hello(
                PROTOCOL_VERSION,
                SessionConfig(
                    session="pano", role="capture", mode="lossless", panorama=PanoramaConfig()
                ),
            )
        )
        assert isinstance(peer.receive(), Welcome)
        y, x = np.mgrid[0:32, 0:64]
        panorama = np.stack([255 - y * 8, 128 + 0 * x, x * 4], axis=-1).astype(np.uint8)
        peer.send_message(Frame(0, 1.0, None, None, None, panorama, "png"))
        result = peer.receive(timeout_s=60)
        assert isinstance(result, Result), result
        np.testing.assert_allclose(
            result.panorama_dominant_direction, _normalized_band1(result.panorama_sh), rtol=1e-9
        )
        np.testing.assert_allclose(result.sh, result.panorama_sh, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(
            result.dominant_direction_world,
            result.panorama_dominant_direction,
            rtol=1e-9,
            atol=1e-12,
        )
        rgb = np.array(result.panorama_sh_rgb)
        np.testing.assert_allclose(
            result.panorama_sh, [0.2126, 0.7152, 0.0722] @ rgb, rtol=1e-6, atol=1e-9
        )
        peer.close()


# --------------------------------------------------------------------------- 4. seq bound


class TestSeqBound:
    """Point 4: seq is 0..2^63-1 everywhere (sections 3, 4 and 6)."""

    def test_section_6_states_the_bound(self):
        errors = spec_section("Error fields")
        assert (
            "`frame.seq` (no `seq`: the Frame header's `seq` is not an integer in\n"
            "0..2^63-1" in errors
        )

    def test_decoder_and_server(self, make_server):
        expect("bad_field", "frame.seq", decode, refused_parts("frame_seq_too_large"))
        server = make_server(process=identity_step())
        stranger = RawPeer(server.connect_address)  # refused on arrival, whoever sends it
        stranger.send(refused_parts("frame_seq_too_large"))
        error = stranger.receive()
        assert (error.code, error.field, error.seq, error.retryable) == (
            "bad_field",
            "frame.seq",
            None,
            False,
        )
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("bound"), Welcome)
        peer.send(refused_parts("frame_seq_too_large"))
        assert peer.receive().field == "frame.seq"
        top = 2**63 - 1
        peer.send(_with_header(VEC.vectors()["frame_raw_raw"], seq=top))
        reply = peer.receive()
        assert reply.seq == top  # accepted (an Error about its 8 x 6 size, with its seq)
        peer.close()
        stranger.close()


# --------------------------------------------------------------------------- 5. versions


class TestVersionRule:
    """Point 5: within a version a peer refuses keys it does not know and other versions, and
    ignores unknown keys of the open maps and unknown Error codes."""

    def test_refusals(self, make_server):
        expect("bad_field", "hello.config.capabilities", decode, refused_parts("hello_unknown_key"))
        expect("bad_version", "v", decode, refused_parts("heartbeat_v3"))
        server = make_server(process=identity_step())
        peer = RawPeer(server.connect_address)
        peer.send(refused_parts("hello_unknown_key"))
        error = peer.receive()
        assert (error.code, error.field, error.retryable) == (
            "bad_field",
            "hello.config.capabilities",
            False,
        )
        peer.send(refused_parts("heartbeat_v3"))
        assert (peer.receive().code, server.snapshot()["sessions"]) == ("bad_version", {})
        peer.close()

    def test_what_a_peer_ignores(self):
        result = decode(
            encode(
                _result(
                    confidence={"value": 0.5, "added_later": [1, 2]},
                    timings_ms={"NewStage": 1.0},
                    diagnostics={"new_key": {"x": 1}},
                )
            )
        )
        assert result.diagnostics == {"new_key": {"x": 1}}
        error = decode(
            encode(
                Error("added_later_code", "a code this client does not know", "some.new.field", 3)
            )
        )
        assert error.retryable is False  # final: the client acts on retryable alone

    def test_the_rule_is_stated(self):
        rule = spec_section("The version rule")
        for phrase in (
            "optional key",
            "What a peer **ignores**",
            "What a peer **refuses**",
            "`v` 3",
            "bad_version",
        ):
            assert phrase in rule, phrase


# --------------------------------------------------------------------------- 6. ambiguities


class TestAmbiguitiesSettled:
    """Point 6: each case SPEC.md left open, as it now reads."""

    def test_truncated_frame_from_an_unknown_peer_gets_the_session_error(self, make_server):
        expect("malformed", "frame.buffers", decode, refused_parts("frame_truncated"))
        server = make_server(process=identity_step())
        stranger = RawPeer(server.connect_address)
        stranger.send(refused_parts("frame_truncated"))
        error = stranger.receive()
        assert (error.code, error.field, error.seq, error.retryable) == (
            "bad_state",
            "session",
            8,
            True,
        )
        capture = RawPeer(server.connect_address)  # from its capture peer: the worker's
        assert isinstance(capture.hello("trunc", width=8, height=6), Welcome)  # decoder
        capture.send(refused_parts("frame_truncated"))
        error = capture.receive()
        assert (error.code, error.field, error.seq, error.retryable) == (
            "malformed",
            "frame.buffers",
            8,
            False,
        )
        stranger.close()
        capture.close()

    def test_bye_unknown_kind_from_an_unknown_peer_is_answered(self, make_server):
        expect("bad_field", "bye.kind", decode, refused_parts("bye_unknown_kind"))
        server = make_server(process=identity_step())
        stranger = RawPeer(server.connect_address)
        stranger.send(refused_parts("bye_unknown_kind"))
        error = stranger.receive()
        assert (error.code, error.field, error.seq) == ("bad_field", "bye.kind", None)
        stranger.send_message(Bye("valid", ByeKind.LEAVING))  # ignored: no answer, so the
        stranger.send_message(Heartbeat(1.0))  # next message answers the Heartbeat
        error = stranger.receive()
        assert (error.code, error.field, error.seq) == ("bad_state", "session", None)
        stranger.close()

    def test_empty_exports_is_refused(self, make_server):
        expect("bad_field", "hello.config.exports", decode, refused_parts("hello_exports_empty"))
        server = make_server(process=identity_step())
        peer = RawPeer(server.connect_address)
        peer.send(refused_parts("hello_exports_empty"))
        error = peer.receive()
        assert (error.code, error.field) == ("bad_field", "hello.config.exports")
        assert server.snapshot()["sessions"] == {}
        peer.close()

    def test_resume_ignores_the_token_as_well_as_the_client_name(self, make_server):
        admin = "admin-token_0123456789"
        server = make_server(process=identity_step(), session_tokens=True, admin_token=admin)
        first = RawPeer(server.connect_address)
        welcome = first.hello("resume", client_name="first", token="session-token_0123456789")
        assert welcome.token == "session-token_0123456789"
        first.send(_frame(0))
        answer = first.receive_raw()
        second = RawPeer(server.connect_address)  # other name, the admin token: resumes
        welcome = second.hello("resume", client_name="second", token=admin)
        assert isinstance(welcome, Welcome) and welcome.token == "session-token_0123456789"
        second.send(_frame(0))  # a duplicate: the same session's cached answer
        assert second.receive_raw() == answer
        third = RawPeer(server.connect_address)  # the same config, a token that admits not
        error = third.hello("resume", token="other-token_0123456789")
        assert (error.code, error.field) == ("unauthorized", "hello.config.token")
        for peer in (first, second, third):
            peer.close()

    def test_spec_says_so(self):
        handshake = spec_section("Handshake")
        assert "every field except `client_name` and `token`" in handshake
        assert "a truncated Frame" in handshake and "`bye.kind`" in handshake
        assert "an empty array is `bad_field`" in spec_section("hello (client")


def _frame(seq: int) -> list[bytes]:
    color = np.full((48, 64, 3), 7, np.uint8)
    depth = np.full((48, 64), 5000, np.uint16)
    return [bytes(p) for p in encode(Frame(seq, 1.0 + seq, color, depth, None, None, "png"))]


# --------------------------------------------------------------------------- 7. repeated keys


class TestRepeatedKeys:
    """Point 7: a map naming a key twice is refused (malformed, header), at any depth."""

    def test_refused_vector(self):
        error = expect("malformed", "header", decode, refused_parts("hello_repeated_key"))
        assert "session" in str(error)

    def test_at_any_depth(self):
        def twice(header):
            header["diagnostics"] = VEC.Pairs([("a", 1), ("a", 2)])
            return header

        expect("malformed", "header", decode, VEC.edited(_result(), twice))

        def twice_top(header):
            return VEC.Pairs([*header.items(), ("seq", 9)])

        expect("malformed", "header", decode, VEC.edited(_result(), twice_top))

    def test_server_refuses_without_making_a_session(self, make_server):
        server = make_server(process=identity_step())
        peer = RawPeer(server.connect_address)
        peer.send(refused_parts("hello_repeated_key"))
        error = peer.receive()
        assert (error.code, error.field, error.seq) == ("malformed", "header", None)
        assert server.snapshot()["sessions"] == {}
        assert isinstance(peer.hello("twice"), Welcome)
        peer.send(
            VEC.edited(
                Frame(3, 1.0, np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.uint16)),
                lambda h: VEC.Pairs([*h.items(), ("seq", 4)]),
            )
        )
        error = peer.receive()  # on arrival, before seq is read: no seq
        assert (error.code, error.field, error.seq) == ("malformed", "header", None)
        peer.close()
