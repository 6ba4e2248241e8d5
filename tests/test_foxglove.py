"""Foxglove: the message mapping, recordings that Foxglove (and `mcap cat --json`) decode,
`arlight display --record` and `--foxglove` over a loopback server, the latency plot.

The recordings are decoded as Foxglove and the mcap CLI do: protobuf from the file's own
FileDescriptorSets (mcap-protobuf-support), JSON as JSON.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import threading
import time

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from streaming_support import flat_source, identity_step, run_with_timeout, server_factory

from arlight.cli import EXIT_BAD_INPUT, main
from arlight.client import foxglove_messages as fx
from arlight.client.capture import CaptureClient, StreamOptions
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.client.latency_plot import fps_over_time, write_latency_plot
from arlight.client.recording import record
from arlight.protocols import Result, decode, peek_header
from arlight.sources.recording import (
    FRAME_TOPIC,
    RESULT_TOPIC,
    Recording,
    RecordingError,
    unpack_parts,
)
from arlight.sources.source import open_source

CAMERA_TOPICS = [fx.COLOR_TOPIC, fx.DEPTH_TOPIC, fx.CALIBRATION_TOPIC, fx.TF_TOPIC]


@pytest.fixture
def make_server():
    yield from server_factory()


def read_topics(path, topics=None) -> dict[str, list]:
    """{topic: [(channel, message, decoded)]}: protobuf decoded with the file's own schemas,
    JSON parsed; other encodings left undecoded (None)."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages(topics=topics):
            if channel.message_encoding == "protobuf":
                decoded = DecoderFactory().decoder_for("protobuf", schema)(message.data)
            elif channel.message_encoding == "json":
                decoded = json.loads(message.data)
            else:
                decoded = None
            out.setdefault(channel.topic, []).append((channel, message, decoded, schema))
    return out


def decoded(message):
    """A foxglove.messages object as the protobuf message a reader of the file gets."""
    from mcap.records import Schema

    schema = type(message).get_schema()
    mcap_schema = Schema(id=1, name=schema.name, encoding=schema.encoding, data=bytes(schema.data))
    return DecoderFactory().decoder_for("protobuf", mcap_schema)(message.encode())


def rotation_of(q) -> np.ndarray:
    """The 3x3 rotation of a decoded Quaternion, or of a foxglove.messages.Quaternion."""
    if not hasattr(q, "x"):
        q = decoded(q)
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


class TestMapping:
    def test_quaternion_round_trips_rotations(self):
        rng = np.random.default_rng(3)
        rotations = [
            np.eye(3),
            np.diag([1.0, -1.0, -1.0]),
            np.diag([-1.0, 1.0, -1.0]),
            np.diag([-1.0, -1.0, 1.0]),
        ]
        for _ in range(20):
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            rotations.append(q * np.sign(np.linalg.det(q)))
        for r in rotations:
            np.testing.assert_allclose(rotation_of(fx.quaternion(r)), r, atol=1e-9)

    @pytest.mark.parametrize("d", [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, 0, -1), (1, 2, -3)])
    def test_arrow_rotation_takes_x_onto_the_direction(self, d):
        d = np.asarray(d, float) / np.linalg.norm(d)
        np.testing.assert_allclose(rotation_of(fx.x_axis_to(d)) @ [1, 0, 0], d, atol=1e-9)

    def test_timestamp_splits_seconds(self):
        t = decoded(fx.composite_image(np.zeros((2, 2, 3), np.uint8), 1700000000.25)).timestamp
        assert (t.seconds, t.nanos) == (1700000000, 250000000)

    def test_lighting_message_is_strict_json(self):
        record = {
            "timestamp": 12.5,
            "frame": 3,
            "sh": [1.0, float("nan")],
            "confidence": {"condition_number": float("inf"), "value": 0.2},
            "timings_ms": {"LightEst": 2.0},
            "end_to_end_ms": None,
        }
        message = fx.lighting_message(record)
        text = json.dumps(message, allow_nan=False)  # raises on NaN / Infinity
        assert json.loads(text)["confidence"] == {"condition_number": None, "value": 0.2}
        assert message["timestamp"] == {"sec": 12, "nsec": 500000000}
        assert message["sh"] == [1.0, None] and message["frame"] == 3

    def test_lighting_message_carries_a_kept_compact_source(self):
        source = {
            "direction_world": [0.0, 0.8, 0.6],
            "direction_camera": [0.0, -0.8, 0.6],
            "intensity": 2.0,
            "rgb": None,
            "angular_radius_deg": 0.27,
            "share": 0.7,
        }
        record = {"timestamp": 1.0, "frame": 0, "compact_sources": [source]}
        assert fx.lighting_message(record)["compact_sources"] == [source]
        assert "compact_sources" not in fx.lighting_message({"timestamp": 1.0, "frame": 0})

    def test_light_scene_arrow_points_towards_the_light(self):
        update = decoded(fx.light_scene([0.0, -1.0, 0.0], 0.7, 5.0))
        (entity,) = update.entities
        assert entity.frame_id == "world" and len(entity.spheres) == 2
        (arrow,) = entity.arrows
        np.testing.assert_allclose(
            rotation_of(arrow.pose.orientation) @ [1, 0, 0], [0, -1, 0], atol=1e-9
        )
        start = np.array([arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z])
        np.testing.assert_allclose(start, np.add(fx.MARKER_CENTRE_M, [0, -fx.MARKER_RADIUS_M, 0]))


class TestRecordings:
    def test_record_writes_camera_topics_foxglove_decodes(self, tmp_path):
        """`arlight record`: colour as sent (JPEG bytes unchanged), depth 16UC1 bit-exact with
        its depth_scale, the calibration, the pose on /tf; the protocol channels still replay."""
        source = open_source(
            "synthetic", synthetic_size=(64, 48), max_frames=3, use_poses=True, synthetic_frames=3
        )
        path = tmp_path / "s.mcap"
        n, _ = record(source, path, StreamOptions(server="tcp://127.0.0.1:1", session="fox"))
        assert n == 3
        topics = read_topics(path)
        assert {
            fx.COLOR_TOPIC: "foxglove.CompressedImage",
            fx.DEPTH_TOPIC: "foxglove.RawImage",
            fx.CALIBRATION_TOPIC: "foxglove.CameraCalibration",
            fx.TF_TOPIC: "foxglove.FrameTransform",
        } == {t: topics[t][0][3].name for t in CAMERA_TOPICS}
        frames = [unpack_parts(m.data, "t") for _, m, _, _ in topics[FRAME_TOPIC]]
        assert all(len(topics[t]) == 3 for t in CAMERA_TOPICS)
        for parts, (_, _, color, _), (channel, _, depth, _), (_, _, tf, _) in zip(
            frames, topics[fx.COLOR_TOPIC], topics[fx.DEPTH_TOPIC], topics[fx.TF_TOPIC], strict=True
        ):
            header, frame = peek_header(parts), decode(parts)
            assert color.format == "jpeg"
            assert color.data == parts[1 + header["color"]["buffer"]]  # the bytes as sent
            assert (depth.encoding, depth.width, depth.height, depth.step) == ("16UC1", 64, 48, 128)
            np.testing.assert_array_equal(
                np.frombuffer(depth.data, "<u2").reshape(48, 64), frame.depth
            )
            assert float(channel.metadata["depth_scale"]) == source.depth_scale
            assert depth.frame_id == color.frame_id == "camera"
            np.testing.assert_allclose(
                [tf.translation.x, tf.translation.y, tf.translation.z], frame.pose[:3, 3]
            )
            np.testing.assert_allclose(rotation_of(tf.rotation), frame.pose[:3, :3], atol=1e-9)
            assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "camera")
            assert color.timestamp.seconds + color.timestamp.nanos * 1e-9 == pytest.approx(
                frame.timestamp
            )
        cal = topics[fx.CALIBRATION_TOPIC][0][2]
        c = source.calibration
        assert list(cal.K) == [c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1]
        assert list(cal.P) == [c.fx, 0, c.cx, 0, 0, c.fy, c.cy, 0, 0, 0, 1, 0]
        assert (cal.width, cal.height) == (64, 48)
        replay = Recording(path)  # the bit-exact replay path is unchanged
        assert replay.num_frames == 3
        assert [p for _, p in replay.frames()] == frames

    def test_raw_colour_is_a_raw_image(self, tmp_path):
        path = tmp_path / "raw.mcap"
        options = StreamOptions(server="tcp://127.0.0.1:1", session="raw", color_codec="raw")
        record(flat_source(2, base=77), path, options)
        (_, _, image, schema), _ = read_topics(path, [fx.COLOR_TOPIC])[fx.COLOR_TOPIC]
        assert schema.name == "foxglove.RawImage" and image.encoding == "rgb8"
        pixels = np.frombuffer(image.data, np.uint8).reshape(48, 64, 3)
        assert (pixels == 77).all()
        assert not read_topics(path, [fx.TF_TOPIC])  # no poses, no /tf


def _stream(server, session: str, frames: int, rate: str = "max", base: int = 10):
    options = StreamOptions(
        server=server.connect_address,
        session=session,
        mode="lossless",
        rate=rate,
        want_composite=True,
        timestamps="capture",
    )
    return run_with_timeout(lambda: CaptureClient(flat_source(frames, base=base), options).run())


class TestDisplayRecord:
    def test_display_records_results_and_plots_latency(self, make_server, tmp_path):
        """`arlight display --record FILE.mcap --out DIR`: every Result as received, its
        composite, light and lighting JSON in Foxglove's schemas, and DIR/latency.png."""
        server = make_server(process=identity_step())
        path, out = tmp_path / "d.mcap", tmp_path / "out"
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="rec",
                record=str(path),
                out_dir=str(out),
                idle_exit_s=30.0,
            )
        )
        got: list[Result] = []
        display.on_result = lambda result, record: got.append(result)
        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        assert _stream(server, "rec", 5).results == 5
        thread.join(30)
        assert not thread.is_alive()
        topics = read_topics(path)
        assert set(topics) == {
            RESULT_TOPIC,
            fx.COMPOSITE_TOPIC,
            fx.TF_TOPIC,
            fx.LIGHT_TOPIC,
            fx.LIGHTING_TOPIC,
        }  # no empty Hello / Frame channels
        results = [decode(unpack_parts(m.data, "r")) for _, m, _, _ in topics[RESULT_TOPIC]]
        assert [r.seq for r in results] == [r.seq for r in got] == list(range(5))
        assert [r.sh for r in results] == [r.sh for r in got]
        lighting = [d for _, _, d, _ in topics[fx.LIGHTING_TOPIC]]
        assert topics[fx.LIGHTING_TOPIC][0][3].encoding == "jsonschema"
        assert [x["frame"] for x in lighting] == list(range(5))
        assert lighting[0]["sh"][0] == pytest.approx(10.0)  # identity step: mean colour
        assert set(lighting[0]["timings_ms"]) == {"Identity"}
        assert all(x["end_to_end_ms"] is not None for x in lighting)
        composites = [d for _, _, d, _ in topics[fx.COMPOSITE_TOPIC]]
        assert len(composites) == 5 and composites[0].format == "jpeg"
        for (_, m, _, _), image in zip(topics[RESULT_TOPIC], composites, strict=True):
            parts = unpack_parts(m.data, "r")  # the JPEG as the server sent it, not re-encoded
            assert image.data == parts[1 + peek_header(parts)["composite"]["buffer"]]
        image = cv2.imdecode(np.frombuffer(composites[3].data, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (48, 64, 3) and abs(float(image.mean()) - 13) < 3
        light = topics[fx.LIGHT_TOPIC][0][2]
        assert len(light.entities) == 1 and len(light.entities[0].arrows) == 1
        assert topics[fx.TF_TOPIC][0][2].child_frame_id == "camera"
        with pytest.raises(RecordingError, match="display's recording"):
            Recording(path)  # not a stream to replay: the error says what it is
        plot = cv2.imread(str(out / "latency.png"))
        assert display.plot_path == out / "latency.png" and plot is not None
        assert plot.shape[0] > 300 and plot.std() > 10  # a drawn figure, not blank


class FoxgloveClient:
    """The client side of Foxglove's WebSocket protocol, just enough for a test: handshake,
    read text (JSON ops) and binary frames, subscribe."""

    def __init__(self, port: int, timeout_s: float = 10.0):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            "Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n\r\n".encode()
        )
        self.buffer = b""
        while b"\r\n\r\n" not in self.buffer:
            self.buffer += self.sock.recv(4096)
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        self.status = head.split(b"\r\n")[0].decode()

    def _need(self, n: int) -> None:
        while len(self.buffer) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self.buffer += chunk

    def frame(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next frame (1 text, 2 binary)."""
        self._need(2)
        n, offset = self.buffer[1] & 127, 2
        if n == 126:
            self._need(4)
            n, offset = struct.unpack(">H", self.buffer[2:4])[0], 4
        elif n == 127:
            self._need(10)
            n, offset = struct.unpack(">Q", self.buffer[2:10])[0], 10
        self._need(offset + n)
        opcode, data = self.buffer[0] & 15, self.buffer[offset : offset + n]
        self.buffer = self.buffer[offset + n :]
        return opcode, data

    def send_json(self, message: dict) -> None:
        data, mask = json.dumps(message).encode(), os.urandom(4)
        assert len(data) < 126
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        self.sock.sendall(bytes([0x81, 0x80 | len(data)]) + mask + masked)

    def close(self) -> None:
        self.sock.close()


class TestLiveFoxglove:
    def test_display_serves_the_session_over_foxglove_websocket(self, make_server):
        """`arlight display --foxglove --port 0`: the Foxglove app's protocol advertises the
        composite, light, lighting and /tf channels and streams each Result's messages."""
        server = make_server(process=identity_step())
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="live",
                foxglove=("127.0.0.1", 0),
                idle_exit_s=30.0,
            )
        )
        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        client = FoxgloveClient(display.foxglove.port)
        try:
            assert "101" in client.status
            opcode, data = client.frame()
            assert opcode == 1 and json.loads(data)["op"] == "serverInfo"
            streamer = threading.Thread(
                target=_stream, args=(server, "live", 40, "native"), daemon=True
            )
            streamer.start()
            channels: dict[str, dict] = {}
            deadline = time.monotonic() + 20
            while len(channels) < 4 and time.monotonic() < deadline:
                opcode, data = client.frame()
                if opcode == 1 and json.loads(data)["op"] == "advertise":
                    channels.update({c["topic"]: c for c in json.loads(data)["channels"]})
            assert {fx.COMPOSITE_TOPIC, fx.LIGHT_TOPIC, fx.LIGHTING_TOPIC, fx.TF_TOPIC} <= set(
                channels
            )
            assert channels[fx.COMPOSITE_TOPIC]["schemaName"] == "foxglove.CompressedImage"
            assert channels[fx.LIGHT_TOPIC]["schemaName"] == "foxglove.SceneUpdate"
            assert channels[fx.LIGHTING_TOPIC]["encoding"] == "json"
            time.sleep(0.3)  # the SDK refuses a subscribe that follows its advertise at once
            client.send_json(
                {
                    "op": "subscribe",
                    "subscriptions": [{"id": 7, "channelId": channels[fx.LIGHTING_TOPIC]["id"]}],
                }
            )
            frames_seen = []
            while len(frames_seen) < 3 and time.monotonic() < deadline:
                opcode, data = client.frame()
                if opcode == 2 and data[0] == 1:  # message data: op, u32 sub id, u64 time
                    assert struct.unpack("<I", data[1:5])[0] == 7
                    frames_seen.append(json.loads(data[13:])["frame"])
            assert len(frames_seen) == 3 and frames_seen == sorted(frames_seen)
            streamer.join(30)
        finally:
            client.close()
            thread.join(30)
        assert not thread.is_alive() and display.foxglove is None  # closed at the end

    def test_stream_serves_the_camera_over_foxglove_websocket(self, make_server):
        """`arlight stream --foxglove`: the capture side's colour, depth and calibration go
        live beside the Results (FoxgloveStream as the capture client's recorder)."""
        from mcap.records import Schema

        from arlight.client.foxglove_sinks import FoxgloveStream, LiveSink, Recorders
        from arlight.protocols import received_record

        server = make_server(process=identity_step())
        live = FoxgloveStream(LiveSink("127.0.0.1", 0))
        client = FoxgloveClient(live.sink.port)
        options = StreamOptions(
            server=server.connect_address,
            session="cam",
            mode="lossless",
            rate="native",
            want_composite=True,
            timestamps="capture",
        )
        capture = CaptureClient(
            flat_source(40, base=90),
            options,
            recorder=Recorders(None, live),
            on_result=lambda r, t: live.write_result(r, received_record(r, t), time.time_ns()),
        )
        streamer = threading.Thread(target=lambda: run_with_timeout(capture.run), daemon=True)
        try:
            assert json.loads(client.frame()[1])["op"] == "serverInfo"
            streamer.start()
            channels: dict[str, dict] = {}
            deadline = time.monotonic() + 20
            while len(channels) < 7 and time.monotonic() < deadline:
                opcode, data = client.frame()
                if opcode == 1 and json.loads(data)["op"] == "advertise":
                    channels.update({c["topic"]: c for c in json.loads(data)["channels"]})
            assert set(CAMERA_TOPICS[:3]) | {fx.COMPOSITE_TOPIC, fx.LIGHTING_TOPIC} <= set(channels)
            depth = channels[fx.DEPTH_TOPIC]
            assert depth["metadata"]["depth_scale"] == "5000.0"  # flat_source's scale
            time.sleep(0.3)  # the SDK refuses a subscribe that follows its advertise at once
            client.send_json(
                {"op": "subscribe", "subscriptions": [{"id": 3, "channelId": depth["id"]}]}
            )
            schema = Schema(
                id=1,
                name=depth["schemaName"],
                encoding="protobuf",
                data=base64.b64decode(depth["schema"]),
            )
            decoder = DecoderFactory().decoder_for("protobuf", schema)
            while time.monotonic() < deadline:
                opcode, data = client.frame()
                if opcode == 2 and data[0] == 1:
                    image = decoder(data[13:])
                    break
            assert (image.encoding, image.width, image.height) == ("16UC1", 64, 48)
            assert (np.frombuffer(image.data, "<u2") == 7500).all()  # flat_source: 1.5 m
        finally:
            client.close()
            streamer.join(30)
            live.close()


class TestLatencyPlot:
    def test_fps_over_time(self):
        t = 0.03 + np.arange(30) * 0.1  # 10 Results per second
        fps = fps_over_time(t)
        assert fps[0] == 0.0
        np.testing.assert_allclose(fps[1:], 10.0, atol=1e-6)
        burst = fps_over_time([0.0, 0.5, 1.5, 1.6, 1.7])  # a stall, then 10 per second
        np.testing.assert_allclose(burst, [0.0, 2.0, 1.0, 10.0, 10.0])

    def test_write_latency_plot(self, tmp_path):
        path = write_latency_plot(
            tmp_path / "p" / "l.png", [0.0, 0.1, 0.2, 0.35], [10.0, 12.0, 11.0, 30.0], "end-to-end"
        )
        assert cv2.imread(str(path)) is not None


class TestCli:
    @pytest.mark.parametrize(
        "argv, flag",
        [
            (["--port", "9000"], "--port"),
            (["--http", "localhost:http"], "--http"),
            (["--record", "x.json"], "--record"),
        ],
    )
    def test_bad_display_options_name_their_flag(self, argv, flag, capsys):
        code = main(["display", "--server", "tcp://127.0.0.1:9", "--session", "s", *argv])
        assert code == EXIT_BAD_INPUT
        assert flag in capsys.readouterr().err

    def test_stream_port_needs_foxglove(self, capsys):
        code = main(
            [
                "stream",
                "synthetic",
                "--server",
                "tcp://127.0.0.1:9",
                "--size",
                "32x24",
                "--max-frames",
                "1",
                "--port",
                "9000",
            ]
        )
        assert code == EXIT_BAD_INPUT and "--foxglove" in capsys.readouterr().err

    def test_foxglove_port_in_use_is_an_error_naming_the_flag(self, capsys):
        with socket.socket() as busy:
            busy.bind(("127.0.0.1", 0))
            busy.listen()
            port = busy.getsockname()[1]
            code = main(
                [
                    "display",
                    "--server",
                    "tcp://127.0.0.1:9",
                    "--session",
                    "s",
                    "--foxglove",
                    "--port",
                    str(port),
                ]
            )
        err = capsys.readouterr().err
        assert code == 1 and "--foxglove/--port" in err and "Traceback" not in err
