"""The 360-degree panorama in the service (issue 12, item 7): the wire fields, panorama-only
sessions, RGB-D + panorama sessions, light_source, malformed panoramas; real sockets on
loopback (tcp://127.0.0.1:*)."""

from __future__ import annotations

import math

import cv2
import msgpack
import numpy as np
import pytest
from streaming_support import (
    RawPeer,
    flat_source,
    identity_step,
    run_with_timeout,
    server_factory,
)

from arlight.client.capture import StreamOptions, stream
from arlight.ibl import run as ibl_run
from arlight.pipeline import sh as sh_lib
from arlight.pipeline.ibl import IblParams
from arlight.protocols import (
    PROTOCOL_VERSION,
    Error,
    Frame,
    Hello,
    PanoramaConfig,
    ProtocolError,
    Result,
    SessionConfig,
    Welcome,
    decode,
    encode,
)
from arlight.sources.panorama import open_panorama
from arlight.sources.panorama_stream import (
    is_panorama_input,
    panorama_only_source,
    with_panorama,
)
from arlight.sources.synthetic_panorama import (
    keyed_exposure,
    ldr_frame,
    sun_direction,
    synthetic_sky,
)

YAW_90 = (0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0)  # panorama_from_world: 90 deg about +y


@pytest.fixture
def make_server():
    yield from server_factory()


def _sky_frames(n: int = 3, width: int = 128) -> list[np.ndarray]:
    """LDR 2:1 frames of the built-in sky turning about +y (one exposure)."""
    first = synthetic_sky(width, sun_direction(math.radians(35), 0.0))
    exposure = keyed_exposure(first, 0.18)
    return [
        ldr_frame(synthetic_sky(width, sun_direction(math.radians(35), i * 0.7)), exposure=exposure)
        for i in range(n)
    ]


@pytest.fixture
def sky_video(tmp_path):
    """A lossless-enough video is not needed: both sides decode the same file."""
    path = tmp_path / "sky.avi"
    frames = _sky_frames(4)
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def _result(**extra) -> Result:
    sh = [0.1 * i for i in range(16)]
    return Result(
        seq=1,
        timestamp=2.0,
        sh=sh,
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
        server_finish_time=1.5,
        **extra,
    )


def _pano_fields(sh=None) -> dict:
    sh = sh or [0.2] * 16
    return dict(
        panorama_sh=sh, panorama_sh_rgb=[sh, sh, sh], panorama_dominant_direction=[0.0, 1.0, 0.0]
    )


# --------------------------------------------------------------------------- wire


class TestWire:
    def test_result_panorama_fields_round_trip(self):
        msg = _result(**_pano_fields([0.5 - 0.01 * i for i in range(16)]))
        got = decode(encode(msg))
        assert got.panorama_sh == msg.panorama_sh
        assert got.panorama_sh_rgb == msg.panorama_sh_rgb
        assert got.panorama_dominant_direction == [0.0, 1.0, 0.0]

    def test_a_result_without_panorama_has_no_panorama_keys(self):
        """Old peers: a Result of a frame without panorama is what it was, byte for byte
        (the golden vectors from before are unchanged); absent keys decode as None."""
        header = msgpack.unpackb(bytes(encode(_result())[0]), raw=False)
        assert not [k for k in header if k.startswith("panorama")]
        got = decode(encode(_result()))
        assert got.panorama_sh is None and got.panorama_dominant_direction is None

    def test_panorama_keys_come_all_three_or_none(self):
        fields = _pano_fields()
        del fields["panorama_sh_rgb"]
        with pytest.raises(ProtocolError) as info:
            encode(_result(**fields))
        assert info.value.field == "result.panorama_sh_rgb"
        # a header that carries only some of them is refused on decode too
        parts = encode(_result(**_pano_fields()))
        header = msgpack.unpackb(bytes(parts[0]), raw=False)
        del header["panorama_dominant_direction"]
        with pytest.raises(ProtocolError) as info:
            decode([msgpack.packb(header), *parts[1:]])
        assert info.value.field == "result.panorama_dominant_direction"

    def test_panorama_sh_must_be_l_squared(self):
        with pytest.raises(ProtocolError) as info:
            encode(_result(**_pano_fields([0.1] * 15)))
        assert info.value.field == "result.panorama_sh"

    def test_panorama_only_frame(self):
        pano = _sky_frames(1, 32)[0]
        got = decode(encode(Frame(3, 1.0, None, None, panorama=pano, color_codec="png")))
        assert got.color is None and got.depth is None
        np.testing.assert_array_equal(got.panorama, pano)
        with pytest.raises(ProtocolError) as info:  # nothing at all
            encode(Frame(3, 1.0, None, None))
        assert info.value.field == "frame.panorama"
        with pytest.raises(ProtocolError) as info:  # depth without colour
            encode(Frame(3, 1.0, None, np.zeros((4, 4), np.uint16), panorama=pano))
        assert info.value.field == "frame.color"

    def test_hello_panorama_config(self):
        hello = Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="p", role="capture", panorama=PanoramaConfig("paper", "panorama", YAW_90)
            ),
        )
        got = decode(encode(hello))
        assert got.config.panorama == PanoramaConfig("paper", "panorama", YAW_90)
        assert got.config.calibration is None  # panorama-only: no camera
        bad = SessionConfig(
            session="p",
            role="capture",
            panorama=PanoramaConfig(panorama_from_world=(2.0,) + YAW_90[1:]),
        )
        with pytest.raises(ProtocolError) as info:
            encode(Hello(PROTOCOL_VERSION, bad))
        assert info.value.field == "hello.config.panorama.panorama_from_world"
        with pytest.raises(ProtocolError) as info:
            encode(
                Hello(
                    PROTOCOL_VERSION,
                    SessionConfig(
                        session="p", role="capture", panorama=PanoramaConfig(light_source="sun")
                    ),
                )
            )
        assert info.value.field == "hello.config.panorama.light_source"
        with pytest.raises(ProtocolError) as info:  # capture without calibration nor panorama
            encode(Hello(PROTOCOL_VERSION, SessionConfig(session="p", role="capture")))
        assert info.value.field == "hello.config.calibration"


# --------------------------------------------------------------------------- sources


def test_panorama_sources(sky_video, tmp_path):
    assert is_panorama_input(str(sky_video))
    assert not is_panorama_input("synthetic")
    source = panorama_only_source(str(sky_video))
    frames = list(source.frames())
    assert source.calibration is None and len(frames) == 4
    assert all(f.color is None and f.panorama.shape == (64, 128, 3) for f in frames)
    assert len(list(source.frames())) == 4  # a second pass opens the video again
    both = with_panorama(flat_source(3), str(sky_video))
    paired = list(both.frames())
    assert len(paired) == 3 and all(f.color is not None and f.panorama is not None for f in paired)


# --------------------------------------------------------------------------- service


def _offline(path, operator: str) -> list:
    """What `arlight ibl PATH --operator OP` computes for each frame (its own code path)."""
    records = []
    source = open_panorama(path)
    ibl_run(source, IblParams(operator=operator), records.append)
    return records


class TestPanoramaOnlySession:
    def test_results_equal_arlight_ibl_offline(self, make_server, sky_video):
        server = make_server()  # the real session code (no RGB-D pipeline is built)
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address,
            session="pano-only",
            mode="lossless",
            rate="max",
            color_codec="png",
            panorama=PanoramaConfig("paper"),
        )
        summary = run_with_timeout(
            lambda: stream(
                panorama_only_source(str(sky_video)),
                options,
                on_result=lambda r, _: results.append(r),
            )
        )
        assert summary.errors == [] and len(results) == 4
        offline = _offline(sky_video, "paper")
        for got, want in zip(results, offline, strict=True):
            np.testing.assert_allclose(got.panorama_sh, want.result.sh, rtol=1e-6, atol=1e-9)
            np.testing.assert_allclose(
                got.panorama_sh_rgb, want.result.sh_rgb, rtol=1e-6, atol=1e-9
            )
            np.testing.assert_allclose(
                got.panorama_dominant_direction, want.result.dominant_direction, atol=1e-9
            )
            # identity panorama_from_world: the world light is the panorama's
            np.testing.assert_allclose(got.sh, want.result.sh, rtol=1e-6, atol=1e-9)
            assert got.diagnostics["light_source"] == "panorama"
            assert got.diagnostics["panorama_operator"] == "paper"
            assert got.pose == np.eye(4).tolist() and got.composite is None
            assert "PanoramaSH" in got.timings_ms

    def test_panorama_from_world_rotates_the_world_light(self, make_server):
        server = make_server()
        peer = RawPeer(server.connect_address)
        peer.send_message(
            Hello(
                PROTOCOL_VERSION,
                SessionConfig(
                    session="rotated",
                    role="capture",
                    mode="lossless",
                    panorama=PanoramaConfig(panorama_from_world=YAW_90),
                ),
            )
        )
        assert isinstance(peer.receive(), Welcome)
        pano = _sky_frames(1)[0]
        peer.send_message(Frame(0, 1.0, None, None, panorama=pano, color_codec="png"))
        got = peer.receive()
        assert isinstance(got, Result)
        r = np.array(YAW_90).reshape(3, 3)
        d_pano = np.array(got.panorama_dominant_direction)
        np.testing.assert_allclose(got.dominant_direction_world, r.T @ d_pano, atol=1e-9)
        np.testing.assert_allclose(got.sh, sh_lib.rotate(got.panorama_sh, r.T), atol=1e-9)
        # the world direction is where the light is: the world light evaluated there peaks
        np.testing.assert_allclose(
            sh_lib.dominant_direction(np.array(got.sh)), got.dominant_direction_world, atol=1e-6
        )
        peer.close()

    def test_rgbd_frame_in_a_panorama_only_session_is_an_error(self, make_server):
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
        color = np.zeros((48, 64, 3), np.uint8)
        peer.send_message(Frame(0, 1.0, color, np.zeros((48, 64), np.uint16)))
        error = peer.receive()
        assert isinstance(error, Error) and error.field == "frame.color" and error.seq == 0
        peer.close()

    def test_unknown_operator_refuses_the_hello(self, make_server):
        server = make_server()
        peer = RawPeer(server.connect_address)
        peer.send_message(
            Hello(
                PROTOCOL_VERSION,
                SessionConfig(session="pano", role="capture", panorama=PanoramaConfig("nosuch")),
            )
        )
        error = peer.receive()
        assert isinstance(error, Error) and error.field == "hello.config.panorama.operator"
        peer.close()


class TestRgbdWithPanorama:
    def test_result_reports_both_and_light_source_chooses(self, make_server, sky_video):
        seen: list = []
        identity = identity_step()

        def step(frame, session, render_light, deadline):  # what the Pipeline would be given
            seen.append((session.name, render_light))
            return identity(frame, session, render_light, deadline)

        server = make_server(process=step)
        offline = _offline(sky_video, "boost")
        for light_source in ("rgbd", "panorama"):
            results: list[Result] = []
            options = StreamOptions(
                server=server.connect_address,
                session=light_source,
                mode="lossless",
                rate="max",
                color_codec="png",
                panorama=PanoramaConfig(light_source=light_source),
            )
            source = with_panorama(flat_source(3), str(sky_video))

            def run(source=source, options=options, results=results):
                return stream(source, options, on_result=lambda r, _: results.append(r))

            summary = run_with_timeout(run)
            assert summary.errors == [] and len(results) == 3
            for i, got in enumerate(results):
                # the RGB-D estimate (the identity step's: sh[0] = mean colour) ...
                assert got.sh[0] == pytest.approx(10 + i)
                # ... and the panorama's light, as arlight ibl computes it offline
                np.testing.assert_allclose(
                    got.panorama_sh, offline[i].result.sh, rtol=1e-6, atol=1e-9
                )
                assert got.diagnostics["light_source"] == light_source
            lights = [light for name, light in seen if name == light_source]
            if light_source == "rgbd":
                assert lights == [None, None, None]
            else:
                for i, (sh_world, rgb_world, environment) in enumerate(lights):
                    assert environment is None  # no virtual object reflects: no mip pyramid
                    np.testing.assert_allclose(sh_world, offline[i].result.sh, rtol=1e-6, atol=1e-9)
                    np.testing.assert_allclose(
                        rgb_world, offline[i].result.sh_rgb, rtol=1e-6, atol=1e-9
                    )


class TestReflectingObjects:
    def test_a_mirror_object_gets_the_panoramas_hdr_map_to_reflect(self, make_server, sky_video):
        """light_source "panorama" with a mirror among the virtual objects: the Pipeline is
        also given the panorama's HDR map (its mip pyramid) and map_from_world."""
        from arlight.pipeline.rendering import EnvironmentMap
        from arlight.pipeline.virtual_scene import Material, VirtualScene, object_from_open3d
        from arlight.pipeline.virtual_scene import sphere_mesh as ball

        seen: list = []
        identity = identity_step()

        def step(frame, session, render_light, deadline):
            seen.append(render_light)
            return identity(frame, session, render_light, deadline)

        server = make_server(process=step)
        mirror = object_from_open3d(
            "mirror", ball(0.1), np.eye(4), Material((0.9, 0.9, 0.9), mirror=True)
        )
        options = StreamOptions(
            server=server.connect_address,
            session="reflect",
            mode="lossless",
            rate="max",
            color_codec="png",
            scene=VirtualScene((mirror,)),
            panorama=PanoramaConfig(light_source="panorama"),
        )
        summary = run_with_timeout(
            lambda: stream(with_panorama(flat_source(2), str(sky_video)), options)
        )
        assert summary.errors == [] and len(seen) == 2
        from arlight.pipeline.inverse_tone import expand

        with open_panorama(str(sky_video)) as source:
            frames = [image for _, image in source]
        for i, (_, _, environment) in enumerate(seen):
            assert isinstance(environment, EnvironmentMap)
            np.testing.assert_array_equal(environment.map_from_world, np.eye(3))
            assert environment.pyramid.num_levels > 3
            # level 0 is the HDR map of the same frame (the session's operator, boost)
            np.testing.assert_allclose(
                environment.pyramid.levels[0], expand(frames[i], "boost"), rtol=1e-6, atol=1e-7
            )


class TestMalformedPanorama:
    def test_not_2_to_1_is_an_error_for_that_frame_only(self, make_server):
        server = make_server(process=identity_step())
        good = _sky_frames(1, 64)[0]
        bad = np.zeros((40, 60, 3), np.uint8)
        only = RawPeer(server.connect_address)
        only.send_message(
            Hello(
                PROTOCOL_VERSION,
                SessionConfig(
                    session="only", role="capture", mode="lossless", panorama=PanoramaConfig()
                ),
            )
        )
        assert isinstance(only.receive(), Welcome)
        rgbd = RawPeer(server.connect_address)
        assert isinstance(rgbd.hello("rgbd"), Welcome)
        other = RawPeer(server.connect_address)
        assert isinstance(other.hello("other"), Welcome)
        color = np.full((48, 64, 3), 7, np.uint8)
        depth = np.full((48, 64), 7500, np.uint16)
        for seq in range(3):
            pano = bad if seq == 1 else good
            only.send_message(Frame(seq, 1.0 + seq, None, None, panorama=pano, color_codec="png"))
            rgbd.send_message(Frame(seq, 1.0 + seq, color, depth, panorama=pano, color_codec="png"))
            other.send_message(Frame(seq, 1.0 + seq, color, depth, color_codec="png"))
        for peer in (only, rgbd):
            replies = [peer.receive() for _ in range(3)]
            assert [type(r).__name__ for r in replies] == ["Result", "Error", "Result"]
            error = replies[1]
            assert error.seq == 1 and error.code == "bad_field"
            assert error.field == "frame.panorama" and not error.retryable
            assert "2:1" in error.message and "60x40" in error.message
            assert replies[2].panorama_sh is not None
        replies = [other.receive() for _ in range(3)]
        assert all(isinstance(r, Result) and r.panorama_sh is None for r in replies)
        assert set(server.snapshot()["sessions"]) >= {"only", "rgbd", "other"}
        for peer in (only, rgbd, other):
            peer.close()


# --------------------------------------------------------------------------- rendering


def test_pipeline_renders_with_the_given_light():
    """Pipeline.process(render_light=...): the objects are lit by the given (panorama) SH
    instead of the estimate, which is still made and returned unchanged."""
    from arlight.pipeline.color import LUMA
    from arlight.pipeline.config import Config
    from arlight.pipeline.pipeline import Pipeline
    from arlight.pipeline.virtual_scene import (
        Anchor,
        Material,
        VirtualScene,
        object_from_open3d,
        sphere_mesh,
    )
    from arlight.sources.synthetic import make_sequence

    seq = make_sequence(num_frames=1, width=160, height=120, sensor_noise=False)
    frame = seq.frames[0]

    def run(render_light):
        obj = object_from_open3d(
            "ball", sphere_mesh(0.08), np.eye(4), Material((0.6, 0.6, 0.6)), Anchor((80.0, 85.0))
        )
        pipe = Pipeline(
            Config.from_preset("full", volume_resolution=64, aux_resolution=32),
            seq.camera,
            VirtualScene((obj,)),
        )
        result = pipe.process(frame, render_light=render_light)
        return result, pipe.last_render

    estimate, (inputs_est, out_est) = run(None)
    bright = np.zeros(16)
    bright[0] = 4.0
    rgb = np.stack([bright, bright * 0.5, bright * 0.25])
    lit, (inputs_pano, out_pano) = run((bright, rgb))
    np.testing.assert_array_equal(lit.sh, estimate.sh)  # the estimate does not change
    np.testing.assert_array_equal(inputs_pano.light_sh, bright)
    np.testing.assert_allclose(inputs_pano.light_rgb @ LUMA, 1.0, rtol=0.05)
    assert inputs_pano.light_rgb[0] > inputs_pano.light_rgb[2]  # the panorama's colour
    mask = out_pano.virtual_mask
    assert mask.sum() > 20
    assert np.any(out_pano.composite[mask] != out_est.composite[mask])


def test_the_json_record_carries_the_panorama_light():
    from arlight.protocols import result_record

    assert "panorama_sh" not in result_record(_result())
    record = result_record(_result(**_pano_fields()))
    assert record["panorama_dominant_direction"] == [0.0, 1.0, 0.0]
    assert len(record["panorama_sh_rgb"]) == 3


def test_arlight_stream_a_360_video(make_server, sky_video, tmp_path, capsys):
    """`arlight stream pano.avi --server ...`: a 2:1 video as SOURCE streams panorama-only
    frames; a non-2:1 image is refused before anything is sent (exit 2)."""
    import json

    from arlight.cli import main

    server = make_server()
    out = tmp_path / "results.jsonl"
    assert (
        main(
            [
                "stream",
                str(sky_video),
                "--server",
                server.connect_address,
                "--mode",
                "lossless",
                "--rate",
                "max",
                "--color-codec",
                "png",
                "--panorama-operator",
                "paper",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    records = [json.loads(line) for line in out.read_text().splitlines()]
    offline = _offline(sky_video, "paper")
    assert len(records) == len(offline) == 4
    for got, want in zip(records, offline, strict=True):
        np.testing.assert_allclose(got["panorama_sh"], want.result.sh, rtol=1e-6, atol=1e-9)
    assert "panorama light=(" in capsys.readouterr().out
    narrow = tmp_path / "narrow.png"
    cv2.imwrite(str(narrow), np.zeros((100, 150, 3), np.uint8))
    assert main(["stream", str(narrow), "--server", server.connect_address]) == 2
    assert "2:1" in capsys.readouterr().err
