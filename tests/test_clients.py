"""Capture sources, MCAP recordings (bit-exact replay), the display client and the streaming
commands (`arlight stream / record / display / demo`), over real loopback sockets."""

from __future__ import annotations

import json
import re
import threading
import time

import cv2
import numpy as np
import pytest
import zmq
from streaming_support import (
    DATA,
    TUM_FOLDER,
    flat_source,
    identity_step,
    need_data,
    run_with_timeout,
    server_factory,
)

from arlight.cli import main
from arlight.client.capture import (
    CaptureClient,
    StreamOptions,
    default_session_name,
    encoded_frames,
)
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.client.recording import record
from arlight.core.checks import depth_metres
from arlight.protocols import (
    PROTOCOL_VERSION,
    Frame,
    Heartbeat,
    Hello,
    Result,
    Welcome,
    decode,
    encode,
    peek_header,
)
from arlight.sources.recording import (
    FRAME_TOPIC,
    HELLO_TOPIC,
    INFO_TOPIC,
    Recording,
    RecordingError,
)
from arlight.sources.seven_scenes import SEVEN_SCENES_DEPTH_SCALE
from arlight.sources.source import open_source


@pytest.fixture
def make_server():
    yield from server_factory()


def _bytes(parts) -> list[bytes]:
    return [bytes(memoryview(p)) for p in parts]


class TestSources:
    def test_synthetic(self):
        source = open_source("synthetic", synthetic_size=(64, 48), max_frames=2)
        assert (source.calibration.width, source.calibration.height) == (64, 48)
        frames = list(source.frames())
        assert len(frames) == source.num_frames == 2
        assert frames[0].color.shape == (48, 64, 3) and frames[0].color.dtype == np.uint8
        assert frames[0].depth.shape == (48, 64) and frames[0].depth.dtype == np.uint16
        assert frames[0].pose is None  # the server tracks unless poses are asked for
        assert open_source(
            "synthetic", synthetic_size=(64, 48), max_frames=1, use_poses=True
        ).frames().__next__().pose.shape == (4, 4)

    @pytest.mark.data
    def test_tum_depth_travels_bit_exactly(self):
        """TUM depth is integers at 5000 units per metre: they are sent untouched, so the wire
        integers give back the reader's metres."""
        from arlight.sources.sequence import open_sequence

        folder = need_data(TUM_FOLDER)
        source = open_source(str(folder), max_frames=2)
        assert source.depth_scale == 5000.0
        assert not any("depth_scale" in note for note in source.notes)
        reference = open_sequence(folder, max_frames=2)
        for sent, frame in zip(source.frames(), reference.frames, strict=True):
            assert frame.depth_scale == source.depth_scale
            np.testing.assert_array_equal(sent.depth, frame.depth)  # the stored integers
            metres = depth_metres(sent.depth, source.depth_scale)
            np.testing.assert_array_equal(metres, depth_metres(frame.depth, frame.depth_scale))
            np.testing.assert_array_equal(sent.color, frame.color)

    @pytest.mark.data
    def test_open3d_millimetre_depth_travels_bit_exactly(self):
        """Millimetres go out as the stored millimetres, at 1000 units per metre."""
        from arlight.sources.sequence import open_sequence

        folder = need_data(DATA / "real" / "icl_nuim_livingroom")
        source = open_source(str(folder), max_frames=1)
        assert source.depth_scale in (5000.0, 1000.0)
        assert source.depth_scale == 1000.0  # the sensor's own units, never rescaled
        sent = next(source.frames())
        raw = cv2.imread(str(folder / "depth" / "00000.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(sent.depth, raw)
        frame = open_sequence(folder, max_frames=1).frames[0]
        np.testing.assert_array_equal(
            depth_metres(sent.depth, source.depth_scale),
            depth_metres(frame.depth, frame.depth_scale),
        )

    @pytest.mark.data
    def test_registered_depth_goes_at_the_readers_stated_scale(self):
        """7-Scenes depth is reprojected into the colour camera: the reader quantises it at
        its stated scale, and that is what is sent (no second rounding)."""
        from arlight.sources.sequence import open_sequence

        folder = need_data(DATA / "real" / "7scenes_redkitchen")
        source = open_source(str(folder), max_frames=1)
        assert source.depth_scale == SEVEN_SCENES_DEPTH_SCALE == 5000.0
        assert any("quantised at 5000" in note for note in source.notes)
        np.testing.assert_array_equal(
            next(source.frames()).depth, open_sequence(folder, max_frames=1).frames[0].depth
        )

    def test_float_metres_are_refused(self):
        """A Source sends the sensor's integers: frames of float metres cannot be one."""
        from arlight.sources.source import sequence_source
        from arlight.sources.synthetic import make_sequence

        clean = make_sequence(num_frames=1, width=8, height=6, sensor_noise=False)
        with pytest.raises(ValueError, match="depth_scale None"):
            sequence_source("clean", clean.camera, clean.frames)

    @pytest.mark.data
    def test_tum_folder_over_loopback_gives_the_readers_metres(self, make_server):
        """Streamed losslessly, the server's pipeline gets the metres that reading the folder
        directly gives, bit for bit."""
        from arlight.sources.sequence import open_sequence

        folder = need_data(TUM_FOLDER)
        received = []
        step = identity_step()

        def process(frame, session, render_light, deadline):
            received.append(depth_metres(frame.depth, frame.depth_scale))
            return step(frame, session, render_light, deadline)

        server = make_server(process=process)
        options = StreamOptions(
            server=server.connect_address,
            session="metres",
            mode="lossless",
            rate="max",
            color_codec="png",
            depth_codec="zstd",
        )
        summary = run_with_timeout(
            CaptureClient(open_source(str(folder), max_frames=3), options).run
        )
        assert summary.errors == [] and summary.results == 3
        reference = open_sequence(folder, max_frames=3)
        assert len(received) == 3
        for got, frame in zip(received, reference.frames, strict=True):
            np.testing.assert_array_equal(got, depth_metres(frame.depth, frame.depth_scale))

    def test_default_session_name_is_a_protocol_name(self):
        name = default_session_name("my data set (copy)/x" * 10)
        assert re.fullmatch(r"[A-Za-z0-9_.\-]{1,64}", name)


class TestRecording:
    def _record(self, path, n=3, **options):
        source = flat_source(n, 64, 48)
        opts = StreamOptions(
            session="rec", mode="lossless", color_codec="png", depth_codec="zstd", **options
        )
        assert record(source, path, opts) == (n, "rec")
        return source, opts

    def test_round_trip(self, tmp_path):
        path = tmp_path / "s.mcap"
        source, opts = self._record(path)
        rec = Recording(path)
        assert rec.num_frames == 3
        config = rec.hello.config
        assert (config.session, config.mode, config.depth_scale) == ("rec", "lossless", 5000.0)
        assert config.calibration == source.calibration
        expected = [_bytes(parts) for _, _, parts in encoded_frames(source, opts, "source")]
        assert [parts for _, parts in rec.frames()] == expected
        log_times = [t for t, _ in rec.frames()]
        assert log_times == sorted(log_times) and log_times[0] == 1000 * 10**9

    def test_readable_by_a_generic_mcap_reader(self, tmp_path):
        from mcap.reader import make_reader

        path = tmp_path / "s.mcap"
        self._record(path)
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            topics = {c.topic: c for c in summary.channels.values()}
            # arlight's own channels, and the Foxglove ones beside them (tests/test_foxglove.py)
            assert set(topics) == {
                HELLO_TOPIC,
                FRAME_TOPIC,
                INFO_TOPIC,
                "/camera/color",
                "/camera/depth",
                "/camera/calibration",
            }
            assert topics[FRAME_TOPIC].message_encoding == "msgpack"
            assert topics[INFO_TOPIC].message_encoding == "json"
            assert summary.schemas[topics[INFO_TOPIC].schema_id].encoding == "jsonschema"
            infos = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[INFO_TOPIC])]
            assert [i["seq"] for i in infos] == [0, 1, 2]
            assert infos[0]["color_codec"] == "png" and infos[0]["width"] == 64
            metadata = {m.name: m.metadata for m in reader.iter_metadata()}
            assert metadata["arlight"]["protocol_version"] == str(PROTOCOL_VERSION)

    def test_corrupt_files_are_rejected(self, tmp_path):
        path = tmp_path / "s.mcap"
        self._record(path)
        data = path.read_bytes()
        text = tmp_path / "text.mcap"
        text.write_text("not an mcap file")
        truncated = tmp_path / "truncated.mcap"
        truncated.write_bytes(data[: len(data) // 2])
        with pytest.raises(RecordingError):
            Recording(text)
        with pytest.raises(RecordingError):
            Recording(tmp_path / "absent.mcap")
        with pytest.raises(RecordingError):
            rec = Recording(truncated)
            list(rec.frames())

    def test_looping_a_recording_renumbers_seq_and_keeps_payloads(self, tmp_path):
        path = tmp_path / "s.mcap"
        self._record(path)
        source = open_source(str(path))
        recorded = [parts for _, parts in Recording(path).frames()]
        looped = list(encoded_frames(source, StreamOptions(loop=True, max_frames=7), "source"))
        assert [seq for seq, _, _ in looped] == list(range(7))
        for seq, _, parts in looped:
            assert peek_header(parts)["seq"] == seq
            assert parts[1:] == recorded[seq % 3][1:]  # image payloads untouched
        assert looped[1][2] == recorded[1]  # the first pass is sent exactly as recorded

    def test_replay_sends_the_recorded_bytes(self, tmp_path):
        """What reaches the server's socket is byte for byte what was recorded."""
        path = tmp_path / "s.mcap"
        self._record(path, n=4)
        received: list[list[bytes]] = []

        def answer(message, parts):  # a Result for every Frame
            received.append(parts)
            return _dummy_result(message)

        source = open_source(str(path))
        summary = _stream_to_fake_server(
            answer,
            lambda address: StreamOptions(
                server=address, session="replay", mode="lossless", rate="max"
            ),
            source,
        )
        assert summary.results == 4
        assert received == [parts for _, parts in Recording(path).frames()]


def _dummy_result(frame: Frame) -> Result:
    return Result(
        seq=frame.seq,
        timestamp=frame.timestamp,
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


def _stream_to_fake_server(answer, make_options, source):
    """Stream `source` to a hand-written server on a ROUTER socket: it welcomes the client,
    answers heartbeats, and replies to each Frame with answer(frame, parts) (None: no reply).
    make_options(address) gives the StreamOptions. Returns the stream's summary."""
    router = zmq.Context.instance().socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    done = threading.Event()

    def serve():
        while not done.is_set():
            if not router.poll(50):
                continue
            identity, *parts = router.recv_multipart()
            message = decode(parts)
            if isinstance(message, Hello):
                reply = Welcome(PROTOCOL_VERSION, message.config.session, 2, 1.0)
            elif isinstance(message, Frame):
                reply = answer(message, parts)
            elif isinstance(message, Heartbeat):
                reply = Heartbeat(time.time())
            else:
                reply = None
            if reply is not None:
                router.send_multipart([identity, *encode(reply)])

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        options = make_options(f"tcp://127.0.0.1:{port}")
        return run_with_timeout(lambda: CaptureClient(source, options).run())
    finally:
        done.set()
        thread.join(5)
        router.close(linger=0)


class TestDisplay:
    def test_writes_results_frames_and_video(self, make_server, tmp_path):
        server = make_server(process=identity_step())
        out = tmp_path / "out"
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="show",
                out_dir=str(out),
                video=str(out / "v.mp4"),
                idle_exit_s=30.0,
            )
        )
        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        options = StreamOptions(
            server=server.connect_address,
            session="show",
            mode="lossless",
            rate="max",
            want_composite=True,
            timestamps="capture",
        )
        summary = run_with_timeout(lambda: CaptureClient(flat_source(5), options).run())
        assert summary.results == 5
        thread.join(30)
        assert not thread.is_alive() and display.summary.ended  # Bye at the end of stream
        lines = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
        assert [x["frame"] for x in lines] == list(range(5))
        assert all(x["end_to_end_ms"] is not None and x["end_to_end_ms"] >= 0 for x in lines)
        assert lines[0]["sh"][0] == pytest.approx(10.0)
        frames = sorted((out / "frames").glob("*.png"))
        assert [f.name for f in frames] == [f"{i:06d}.png" for i in range(5)]
        assert cv2.imread(str(frames[0])).shape == (48, 64, 3)
        video = cv2.VideoCapture(str(out / "v.mp4"))
        count = 0
        while video.read()[0]:
            count += 1
        assert count == 5
        info = display.summary.to_dict()
        assert info["results"] == 5 and info["latency_ms"]["kind"] == "end_to_end"

    def test_export_adds_engine_layouts_to_results_jsonl(self, make_server, tmp_path):
        """DisplayOptions.exports (`arlight display --out DIR --export ...`): each line
        carries the layouts of its own SH and pose."""
        from arlight.pipeline.engine_export import camera_exports

        server = make_server(process=identity_step())
        out = tmp_path / "out"
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="exp",
                out_dir=str(out),
                exports=("gltf", "unity"),
                idle_exit_s=30.0,
            )
        )
        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        options = StreamOptions(
            server=server.connect_address, session="exp", mode="lossless", rate="max"
        )
        assert run_with_timeout(lambda: CaptureClient(flat_source(2), options).run()).results == 2
        thread.join(30)
        lines = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
        assert len(lines) == 2
        for line in lines:
            expected = camera_exports(
                np.asarray(line["sh"]), np.asarray(line["pose"]), ("gltf", "unity")
            )
            assert json.loads(json.dumps(expected)) == line["exports"]


class TestCommands:
    def test_demo_writes_frames_results_and_summary(self, tmp_path):
        out = tmp_path / "demo"
        assert main(["demo", "--out", str(out), "--frames", "3", "--size", "96x72"]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["results"] == summary["frames_sent"] == 3
        assert set(summary["timings_ms_median"]) >= {"Reconstruct", "RadTransfer", "LightEst"}
        assert summary["latency_ms"]["median"] > 0 and summary["fps"] > 0
        assert len(list((out / "frames").glob("*.png"))) == 3
        assert len((out / "results.jsonl").read_text().splitlines()) == 3
        # `fast` keeps a compact source where the shadows show one (decision 0062): the
        # scene's sun, found within a few degrees
        sun = summary["compact_source_to_sun_deg"]
        assert 1 <= sun["frames"] <= 3 and sun["median"] < 10.0
        # the SH's own direction travels beside the reported one: the same where no source
        # was kept, the source's replacing it where one was
        kept = []
        for line in (out / "results.jsonl").read_text().splitlines():
            record = json.loads(line)
            own, reported = (
                np.asarray(record["diagnostics"]["sh_direction_world"]),
                np.asarray(record["dominant_direction_world"]),
            )
            kept.append(record["diagnostics"]["compact"]["kept"] > 0)
            assert abs(np.linalg.norm(own) - 1.0) < 1e-6
            if kept[-1]:  # the scene's sky outshines its sun: the two stand apart
                assert np.degrees(np.arccos(np.clip(own @ reported, -1.0, 1.0))) > 2.0
            else:
                np.testing.assert_allclose(own, reported, atol=1e-9)
        assert sum(kept) == sun["frames"]
        assert 0.0 <= summary["sh_direction_error_deg"]["median"] < 30.0
        rho = summary["confidence_vs_error_spearman"]
        assert set(rho) == {"first_moment", "source_to_sun"}
        assert all(v is None or -1.0 <= v <= 1.0 for v in rho.values())

    def test_the_demo_s_spearman_ranks_confidence_against_error(self):
        from arlight.demo import _spearman

        conf = {0: 0.9, 1: 0.5, 2: 0.1, 3: 0.3}
        assert _spearman(conf, {0: 2.0, 1: 5.0, 2: 20.0, 3: 9.0}) == -1.0
        assert _spearman(conf, {0: 20.0, 1: 9.0, 2: 2.0, 3: 5.0}) == 1.0
        assert _spearman(conf, {0: 2.0, 1: float("nan"), 2: 20.0}) is None  # two frames
        assert _spearman({0: 0.5, 1: 0.5, 2: 0.5}, {0: 1.0, 1: 2.0, 2: 3.0}) is None

    def test_stream_record_and_bit_exact_replay(self, make_server, tmp_path, capsys):
        server = make_server(process=identity_step())
        addr = server.connect_address
        first, second = tmp_path / "first.mcap", tmp_path / "replayed.mcap"
        assert (
            main(
                [
                    "stream",
                    "synthetic",
                    "--server",
                    addr,
                    "--session",
                    "cli",
                    "--mode",
                    "lossless",
                    "--rate",
                    "max",
                    "--max-frames",
                    "3",
                    "--size",
                    "64x48",
                    "--color-codec",
                    "png",
                    "--record",
                    str(first),
                    "--out",
                    str(tmp_path / "r.jsonl"),
                ]
            )
            == 0
        )
        assert len((tmp_path / "r.jsonl").read_text().splitlines()) == 3
        assert (
            main(
                [
                    "stream",
                    str(first),
                    "--server",
                    addr,
                    "--session",
                    "again",
                    "--rate",
                    "max",
                    "--record",
                    str(second),
                ]
            )
            == 0
        )
        err = capsys.readouterr().err
        assert "sent as recorded" in err
        assert [p for _, p in Recording(first).frames()] == [
            p for _, p in Recording(second).frames()
        ]
        assert Recording(second).hello.config.mode == "lossless"  # the recording's own mode

    def test_estimate_stream_and_display_write_one_record_layout(self, make_server, tmp_path):
        """docs/reference/output-record.md: the same keys from every command (the
        streaming ones add the delivery fields; estimate adds the error against truth)."""
        from arlight.protocols import result_record

        est = tmp_path / "est.jsonl"
        assert (
            main(
                [
                    "estimate",
                    "synthetic",
                    "--max-frames",
                    "1",
                    "--preset",
                    "mobile",
                    "--out",
                    str(est),
                ]
            )
            == 0
        )
        record = json.loads(est.read_text().splitlines()[0])
        core = [
            "timestamp",
            "frame",
            "sh",
            "sh_camera",
            "sh_rgb",
            "dominant_direction_camera",
            "dominant_direction_world",
            "intensity",
            "confidence",
            "pose",
            "timings_ms",
            "diagnostics",
        ]
        assert list(record) == [*core, "angular_error_deg"]
        assert record["frame"] == 0 and len(record["sh_camera"]) == len(record["sh"])
        assert "tracking_ok" in record["diagnostics"]
        server = make_server(process=identity_step())
        streamed = tmp_path / "s.jsonl"
        assert (
            main(
                [
                    "stream",
                    "synthetic",
                    "--server",
                    server.connect_address,
                    "--session",
                    "records",
                    "--mode",
                    "lossless",
                    "--rate",
                    "max",
                    "--max-frames",
                    "2",
                    "--size",
                    "64x48",
                    "--out",
                    str(streamed),
                ]
            )
            == 0
        )
        lines = [json.loads(x) for x in streamed.read_text().splitlines()]
        assert [x["frame"] for x in lines] == [0, 1]
        assert all(list(x)[: len(core)] == core for x in lines)
        assert list(result_record(_dummy_result(Frame(0, 1.0, None, None)))) == core

    def test_stream_export_writes_engine_layouts_matching_estimates(self, make_server, tmp_path):
        """`arlight stream --out F --export ...`: the server puts the layouts into every
        Result (Hello config.exports), the numbers the exporters give for that Result's own
        world SH and pose; a display of the session receives them without asking."""
        from arlight.pipeline import sh as sh_lib
        from arlight.pipeline.engine_export import to_arcore, to_webxr

        server = make_server(process=identity_step())
        streamed, shown = tmp_path / "s.jsonl", tmp_path / "shown"
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="export",
                out_dir=str(shown),
                idle_exit_s=30.0,
            )
        )
        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        assert (
            main(
                [
                    "stream",
                    "synthetic",
                    "--server",
                    server.connect_address,
                    "--session",
                    "export",
                    "--mode",
                    "lossless",
                    "--rate",
                    "max",
                    "--max-frames",
                    "2",
                    "--size",
                    "64x48",
                    "--out",
                    str(streamed),
                    "--export",
                    "arcore,webxr",
                ]
            )
            == 0
        )
        thread.join(30)
        lines = streamed.read_text().splitlines()
        displayed = [json.loads(x) for x in (shown / "results.jsonl").read_text().splitlines()]
        assert len(lines) == len(displayed) == 2
        assert [d["exports"] for d in displayed] == [json.loads(x)["exports"] for x in lines]
        for line in lines:
            record = json.loads(line)
            assert set(record["exports"]) == {"arcore", "webxr"}
            light = np.asarray(
                record["sh_rgb"] if record["sh_rgb"] is not None else record["sh"], np.float64
            )
            axes = sh_lib.GL_FROM_CV @ np.asarray(record["pose"])[:3, :3].T
            np.testing.assert_allclose(record["exports"]["arcore"], to_arcore(light, axes))
            np.testing.assert_allclose(record["exports"]["webxr"], to_webxr(light, axes))

    def test_record_command(self, tmp_path):
        path = tmp_path / "r.mcap"
        assert (
            main(
                [
                    "record",
                    "synthetic",
                    "--out",
                    str(path),
                    "--max-frames",
                    "2",
                    "--size",
                    "64x48",
                    "--mode",
                    "lossless",
                ]
            )
            == 0
        )
        assert Recording(path).num_frames == 2

    @pytest.mark.parametrize(
        "argv, message",
        [
            (["stream", "/no/such/folder", "--server", "tcp://127.0.0.1:9"], "no such file"),
            (["stream", "synthetic", "--server", "localhost:5555"], "tcp://HOST:PORT"),
            (["record", "synthetic", "--out", "x.txt"], ".mcap"),
            (
                ["display", "--server", "tcp://127.0.0.1:9", "--session", "s", "--video", "v.avi"],
                ".mp4",
            ),
            (["serve", "--bind", "127.0.0.1:5555"], "tcp://HOST:PORT"),
        ],
        ids=[
            "missing source",
            "bad server address",
            "record not mcap",
            "video not mp4",
            "bad bind address",
        ],
    )
    def test_bad_input_exits_2_with_a_message(self, argv, message, capsys):
        assert main(argv) == 2
        assert message in capsys.readouterr().err

    def test_corrupt_recording_exits_2(self, tmp_path, capsys):
        path = tmp_path / "bad.mcap"
        path.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 64)
        assert main(["stream", str(path), "--server", "tcp://127.0.0.1:9"]) == 2
        assert "bad.mcap" in capsys.readouterr().err

    def test_session_refused_by_the_server_exits_2(self, make_server, capsys):
        server = make_server(process=identity_step())
        assert (
            main(
                [
                    "stream",
                    "synthetic",
                    "--server",
                    server.connect_address,
                    "--size",
                    "64x48",
                    "--max-frames",
                    "1",
                    "--set",
                    "sh_bands=99",
                ]
            )
            == 2
        )
        assert "sh_bands" in capsys.readouterr().err

    def test_no_server_exits_1_after_the_reconnect_timeout(self, capsys):
        with zmq.Context.instance().socket(zmq.ROUTER) as probe:  # a port nobody serves
            port = probe.bind_to_random_port("tcp://127.0.0.1")
        assert (
            main(
                [
                    "stream",
                    "synthetic",
                    "--server",
                    f"tcp://127.0.0.1:{port}",
                    "--size",
                    "64x48",
                    "--max-frames",
                    "1",
                    "--reconnect-timeout",
                    "1",
                ]
            )
            == 1
        )
        assert "no arlight server answered" in capsys.readouterr().err

    def test_unknown_mode_is_a_usage_error(self):
        with pytest.raises(SystemExit) as exc:
            main(["stream", "synthetic", "--mode", "sometimes"])
        assert exc.value.code == 2


def test_bye_ends_a_capture_stream(make_server):
    """A capture client's Bye closes its session once idle (displays get Bye too)."""
    server = make_server(process=identity_step())
    options = StreamOptions(
        server=server.connect_address, session="byebye", mode="lossless", rate="max"
    )
    run_with_timeout(lambda: CaptureClient(flat_source(2), options).run())
    for _ in range(100):
        if "byebye" not in server.snapshot()["sessions"]:
            break
        threading.Event().wait(0.02)
    assert "byebye" not in server.snapshot()["sessions"]


def test_lossless_frame_whose_result_was_lost_is_sent_again():
    """A Result lost on the way (a full send queue at the server) does not hang the stream:
    the unanswered frame is sent again after resend_after_s and its answer then counts."""
    seen: list[int] = []

    def answer(message, parts):  # every Frame except the first copy of seq 1
        seen.append(message.seq)
        if message.seq == 1 and seen.count(1) == 1:
            return None  # this Result is "lost"
        return _dummy_result(message)

    summary = _stream_to_fake_server(
        answer,
        lambda address: StreamOptions(
            server=address, session="lost", mode="lossless", rate="max", resend_after_s=0.5
        ),
        flat_source(3),
    )
    assert summary.results == 3 and not summary.errors
    assert summary.reconnects == 0  # the frame came back by the resend timer, not a reconnect
    assert seen.count(1) == 2 and seen.count(0) == 1 and seen.count(2) == 1


def test_refused_hello_fields_name_their_flag():
    """A refusal of a field, or of a key below it (over_budget names
    hello.config.overrides.KEY), names the `arlight stream` flag that sets it."""
    from arlight.client.capture import hello_field_flag

    assert hello_field_flag("hello.config.overrides.robust_iterations") == "--set"
    assert hello_field_flag("hello.config.exports") == "--export"
    assert hello_field_flag("hello.config.panorama.operator") == "--panorama-operator"
    assert hello_field_flag("hello.config.panorama.panorama_from_world").startswith(
        "--light-source"
    )
    assert hello_field_flag("frame.depth") is None and hello_field_flag(None) is None
