"""Where the Foxglove messages go: an MCAP file (`McapSink`, beside arlight's own channels)
or Foxglove's WebSocket protocol, live (`LiveSink`, the foxglove-sdk's server); the two
publishers that feed either: `publish_frame` (a capture Frame) and `publish_result` (a Result);
and `FoxgloveStream`, one stream's state between them (the Hello's calibration, whether the
frames carry poses), which the recorder and `arlight stream --foxglove` share.

A sink has `log(topic, message, log_time_ns)` for a `foxglove.messages` object (protobuf,
the schema from the class), `log_json(topic, schema, data, log_time_ns)` for a JSON message
with its JSON Schema, and `close()`. log_time_ns: nanoseconds since the Unix epoch.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from arlight.client import foxglove_messages as fx
from arlight.client.connection import encoded_image
from arlight.protocols import CameraCalibration, Frame, Hello, ProtocolError, decode, peek_header

log = logging.getLogger(__name__)


class Sink(Protocol):
    """What publish_frame / publish_result write to (McapSink, LiveSink)."""

    def log(self, topic: str, message, log_time_ns: int) -> None: ...

    def log_json(self, topic: str, schema: Mapping, data: Mapping, log_time_ns: int) -> None: ...

    def set_channel_metadata(self, topic: str, metadata: Mapping[str, str]) -> None: ...

    def close(self) -> None: ...


class McapSink:
    """Foxglove channels in an open `mcap.writer.Writer`; schemas registered once per type,
    channels once per topic (protobuf schema = the FileDescriptorSet foxglove-sdk ships)."""

    def __init__(self, writer, channel_metadata: Mapping[str, Mapping[str, str]] | None = None):
        self._writer = writer
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._metadata = {k: dict(v) for k, v in (channel_metadata or {}).items()}

    def _channel(
        self,
        topic: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
    ) -> int:
        if topic not in self._channels:
            if schema_name not in self._schemas:
                self._schemas[schema_name] = self._writer.register_schema(
                    name=schema_name, encoding=schema_encoding, data=schema_data
                )
            self._channels[topic] = self._writer.register_channel(
                topic, message_encoding, self._schemas[schema_name], self._metadata.get(topic, {})
            )
        return self._channels[topic]

    def set_channel_metadata(self, topic: str, metadata: Mapping[str, str]) -> None:
        """Metadata for `topic`'s channel (before its first message), e.g. depth_scale."""
        self._metadata[topic] = dict(metadata)

    def _write(self, topic: str, channel: int, data: bytes, log_time_ns: int) -> None:
        seq = self._sequence.get(topic, 0)
        self._sequence[topic] = seq + 1
        self._writer.add_message(
            channel,
            log_time=int(log_time_ns),
            data=data,
            publish_time=int(log_time_ns),
            sequence=seq,
        )

    def log(self, topic: str, message, log_time_ns: int) -> None:
        schema = type(message).get_schema()
        channel = self._channel(
            topic, schema.name, schema.encoding, bytes(schema.data), schema.encoding
        )
        self._write(topic, channel, message.encode(), log_time_ns)

    def log_json(self, topic: str, schema: Mapping, data: Mapping, log_time_ns: int) -> None:
        channel = self._channel(
            topic,
            str(schema.get("title", topic)),
            "jsonschema",
            json.dumps(schema).encode(),
            "json",
        )
        self._write(topic, channel, json.dumps(data).encode(), log_time_ns)

    def close(self) -> None:
        """Nothing of its own: the writer's owner finishes the file."""


class LiveSink:
    """Foxglove's WebSocket server (foxglove-sdk `start_server`) on host:port, in its own
    logging context, so that the Foxglove app (Open connection -> ws://HOST:PORT) shows the
    session while it runs. port 0 = any free port (`self.port` says which)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8765,
        name: str = "arlight",
        channel_metadata: Mapping[str, Mapping[str, str]] | None = None,
    ):
        import foxglove

        self._foxglove = foxglove
        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}  # the SDK's typed channels, and Channel for JSON
        self._metadata = {k: dict(v) for k, v in (channel_metadata or {}).items()}
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=int(port), context=self._context
            )
        except Exception as exc:  # the SDK raises its own error types for bind failures
            raise OSError(
                f"cannot serve Foxglove's WebSocket protocol on {host}:{port}: {exc}"
            ) from None
        self.host = host
        self.port = int(self._server.port)

    def set_channel_metadata(self, topic: str, metadata: Mapping[str, str]) -> None:
        """Metadata for `topic`'s channel (before its first message), e.g. depth_scale."""
        self._metadata[topic] = dict(metadata)

    def log(self, topic: str, message, log_time_ns: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            channel_type = getattr(self._foxglove.channels, type(message).__name__ + "Channel")
            channel = channel_type(topic, context=self._context, metadata=self._metadata.get(topic))
            self._channels[topic] = channel
        channel.log(message, log_time=int(log_time_ns))

    def log_json(self, topic: str, schema: Mapping, data: Mapping, log_time_ns: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._foxglove.Channel(
                topic,
                schema=dict(schema),
                context=self._context,
                metadata=self._metadata.get(topic),
            )
            self._channels[topic] = channel
        channel.log(dict(data), log_time=int(log_time_ns))

    def close(self) -> None:
        self._server.stop()


def publish_frame(sink: Sink, parts: Sequence, frame, calibration, log_time_ns: int) -> None:
    """One capture Frame on the camera topics: colour (its JPEG/PNG as sent, raw as rgb8),
    depth (16UC1, wire units), the calibration (protocols CameraCalibration or None) and, when
    the frame has a pose, /tf. parts: the Frame's message parts, frame: the decoded
    protocols Frame. Panorama-only frames log nothing."""
    if frame.color is None:
        return
    stamp_s = float(frame.timestamp)
    sink.log(
        fx.COLOR_TOPIC,
        fx.color_image(encoded_image(parts, "color"), frame.color, stamp_s),
        log_time_ns,
    )
    sink.log(fx.DEPTH_TOPIC, fx.depth_image(frame.depth, stamp_s), log_time_ns)
    if calibration is not None:
        sink.log(fx.CALIBRATION_TOPIC, fx.camera_calibration(calibration, stamp_s), log_time_ns)
    if frame.pose is not None:
        sink.log(fx.TF_TOPIC, fx.camera_transform(frame.pose, stamp_s), log_time_ns)


def publish_result(
    sink: Sink,
    result,
    record: Mapping,
    log_time_ns: int,
    with_pose: bool = True,
    parts: Sequence | None = None,
) -> None:
    """One Result: the composite (if it carries one; its JPEG/PNG bytes as received when
    `parts`, the message's parts, are given), the light in 3D, the lighting JSON and
    (with_pose) its camera pose on /tf. record: protocols.received_record of the Result."""
    stamp_s = float(result.timestamp)
    if result.composite is not None:
        image = fx.composite_image(
            result.composite, stamp_s, encoded=encoded_image(parts, "composite")
        )
        sink.log(fx.COMPOSITE_TOPIC, image, log_time_ns)
    if with_pose and result.pose is not None:
        sink.log(fx.TF_TOPIC, fx.camera_transform(np.asarray(result.pose), stamp_s), log_time_ns)
    sink.log(
        fx.LIGHT_TOPIC,
        fx.light_scene(result.dominant_direction_world, float(result.confidence.value), stamp_s),
        log_time_ns,
    )
    sink.log_json(fx.LIGHTING_TOPIC, fx.LIGHTING_SCHEMA, fx.lighting_message(record), log_time_ns)


class FoxgloveStream:
    """One capture stream into a sink: the Hello (calibration, depth_scale), every Frame
    as sent and, when the client gets them, the Results. Also the capture client's
    `recorder` interface (write_hello, write_frame), so `arlight stream --foxglove` hands it
    to CaptureClient as it hands a Recorder."""

    def __init__(self, sink: Sink):
        self.sink = sink
        self.calibration: CameraCalibration | None = None
        self.frame_poses = False  # the frames carry poses: /tf comes from them

    def write_hello(self, parts, log_time_ns: int) -> None:
        hello = decode(list(parts))
        if isinstance(hello, Hello):
            self.calibration = hello.config.calibration
            self.sink.set_channel_metadata(
                fx.DEPTH_TOPIC,
                {
                    "depth_scale": repr(float(hello.config.depth_scale)),
                    "units": "depth_scale units per metre; 0 = missing",
                },
            )

    def write_frame(self, parts, log_time_ns: int | None = None) -> None:
        header = peek_header(parts)
        log_ns = (
            int(round(float(header["timestamp"]) * 1e9))
            if log_time_ns is None
            else int(log_time_ns)
        )
        try:
            frame = decode(list(parts))
        except ProtocolError as exc:  # sent as it is; the server will say so too
            log.warning("frame %s not on the Foxglove topics: %s", header.get("seq"), exc)
            return
        if not isinstance(frame, Frame):
            raise TypeError(f"write_frame takes a Frame's parts, got a {type(frame).__name__}")
        self.frame_poses = self.frame_poses or frame.pose is not None
        publish_frame(self.sink, parts, frame, self.calibration, log_ns)

    def write_result(self, result, record: Mapping, log_time_ns: int, parts=None) -> None:
        publish_result(
            self.sink, result, record, log_time_ns, with_pose=not self.frame_poses, parts=parts
        )

    def close(self) -> None:
        self.sink.close()


class Recorders:
    """Several recorders as one (the capture client takes one): each call goes to all."""

    def __init__(self, *recorders):
        self.recorders = [r for r in recorders if r is not None]

    def write_hello(self, parts, log_time_ns: int) -> None:
        for r in self.recorders:
            r.write_hello(parts, log_time_ns)

    def write_frame(self, parts, log_time_ns: int | None = None) -> None:
        for r in self.recorders:
            r.write_frame(parts, log_time_ns)
