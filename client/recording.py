"""Stream recordings in MCAP, the robotics field's log container (https://mcap.dev).

One file holds one stream exactly as a capture client sends it:
- channel `/arlight/hello`, message encoding `msgpack`: the session's Hello;
- channel `/arlight/frame`, message encoding `msgpack`: every Frame;
- channel `/arlight/frame_info`, message encoding `json` with a JSON Schema: seq, timestamp,
  codecs and sizes of each frame, so generic tools (Foxglove, `mcap cat --json`) can list
  and plot the stream without knowing our wire format;
- a metadata record `arlight` (versions, source, depth scale).

The data of a `msgpack` message is a msgpack array of the ZeroMQ message parts as sent
(each a bin; the first is the protocol's msgpack header, the rest image payloads), so
`arlight stream FILE.mcap` sends the recorded bytes unchanged: a bit-exact replay.
log_time: when the frame was sent (`stream --record`) or, for an offline `arlight record`,
its timestamp; replay at `--rate native` follows the log_time spacing. publish_time: the
frame's own timestamp. Both in nanoseconds.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack

from arlight import __version__
from arlight.protocols import PROTOCOL_VERSION, Hello, ProtocolError, decode, encode, peek_header

HELLO_TOPIC = "/arlight/hello"
FRAME_TOPIC = "/arlight/frame"
INFO_TOPIC = "/arlight/frame_info"
MESSAGE_ENCODING = "msgpack"
PROFILE = "arlight"
MAX_PARTS = 16

FRAME_INFO_SCHEMA = {
    "title": "arlight.FrameInfo",
    "type": "object",
    "properties": {
        "seq": {"type": "integer"},
        "timestamp": {"type": "number", "description": "frame timestamp, sender clock, s"},
        "color_codec": {"type": "string"},
        "depth_codec": {"type": "string"},
        "width": {"type": "integer"},
        "height": {"type": "integer"},
        "bytes": {"type": "integer", "description": "all parts of the message"},
        "has_pose": {"type": "boolean"},
    },
}


class RecordingError(ValueError):
    """An MCAP file that is not a readable arlight recording; the message says why."""


def _pack_parts(parts) -> bytes:
    return msgpack.packb([bytes(memoryview(p)) for p in parts], use_bin_type=True)


def _unpack_parts(data: bytes, where: str) -> list[bytes]:
    try:
        parts = msgpack.unpackb(data, raw=False)
    except Exception as exc:  # msgpack raises many types for bad input
        raise RecordingError(f"{where}: message is not msgpack ({type(exc).__name__})") from None
    if (not isinstance(parts, list) or not 1 <= len(parts) <= MAX_PARTS
            or not all(isinstance(p, bytes) for p in parts)):
        raise RecordingError(f"{where}: expected a msgpack array of 1..{MAX_PARTS} binary "
                             "parts")
    return parts


class Recorder:
    """Writes one stream to an MCAP file. Use as a context manager, or call close()."""

    def __init__(self, path: str | Path, source: str = "", depth_scale: float | None = None):
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=f"arlight {__version__}")
        info_schema = self._writer.register_schema(
            name="arlight.FrameInfo", encoding="jsonschema",
            data=json.dumps(FRAME_INFO_SCHEMA).encode())
        meta = {"protocol_version": str(PROTOCOL_VERSION),
                "data": "msgpack array of the ZeroMQ message parts as sent"}
        self._hello = self._writer.register_channel(HELLO_TOPIC, MESSAGE_ENCODING, 0, meta)
        self._frame = self._writer.register_channel(FRAME_TOPIC, MESSAGE_ENCODING, 0, meta)
        self._info = self._writer.register_channel(INFO_TOPIC, "json", info_schema)
        self._writer.add_metadata("arlight", {
            "arlight_version": __version__, "protocol_version": str(PROTOCOL_VERSION),
            "source": source, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "depth_scale": "" if depth_scale is None else repr(float(depth_scale))})
        self.frames = 0
        self._closed = False

    def write_hello(self, parts, log_time_ns: int) -> None:
        self._writer.add_message(self._hello, log_time=log_time_ns, data=_pack_parts(parts),
                                 publish_time=log_time_ns, sequence=0)

    def write_frame(self, parts, log_time_ns: int | None = None) -> None:
        """One Frame as sent; log_time_ns None = the frame's own timestamp."""
        header = peek_header(parts)
        stamp_ns = int(round(float(header["timestamp"]) * 1e9))
        log_ns = stamp_ns if log_time_ns is None else int(log_time_ns)
        self._writer.add_message(self._frame, log_time=log_ns, data=_pack_parts(parts),
                                 publish_time=stamp_ns, sequence=self.frames)
        color, depth = header.get("color") or {}, header.get("depth") or {}
        info = {"seq": header["seq"], "timestamp": header["timestamp"],
                "color_codec": color.get("format", ""), "depth_codec": depth.get("format", ""),
                "width": color.get("width", 0), "height": color.get("height", 0),
                "bytes": sum(len(memoryview(p)) for p in parts),
                "has_pose": header.get("pose") is not None}
        self._writer.add_message(self._info, log_time=log_ns, data=json.dumps(info).encode(),
                                 publish_time=stamp_ns, sequence=self.frames)
        self.frames += 1

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Recording:
    """A recording opened for reading: the Hello, and the frames in file order (lazily)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: no such file; record one with "
                                 "`arlight record SOURCE --out FILE.mcap`")
        self.hello_parts: list[bytes] | None = None
        self.metadata: dict[str, str] = {}
        self.num_frames = 0
        with open(self.path, "rb") as f:
            reader = self._reader(f)
            try:
                summary = reader.get_summary()
                for record in reader.iter_metadata():
                    if record.name == "arlight":
                        self.metadata = dict(record.metadata)
                for _, _, message in reader.iter_messages(topics=[HELLO_TOPIC]):
                    self.hello_parts = _unpack_parts(message.data, f"{self.path} {HELLO_TOPIC}")
                    break
            except RecordingError:
                raise
            except Exception as exc:  # mcap raises many types for corrupt files
                raise RecordingError(f"{self.path}: not a readable MCAP file "
                                     f"({type(exc).__name__}: {exc})") from None
        if self.hello_parts is None:
            raise RecordingError(f"{self.path}: no {HELLO_TOPIC} message; this is not an "
                                 "arlight recording (make one with `arlight record`)")
        try:
            hello = decode(self.hello_parts)
        except ProtocolError as exc:
            raise RecordingError(f"{self.path}: the recorded Hello does not decode: {exc}") \
                from None
        if not isinstance(hello, Hello):
            raise RecordingError(f"{self.path}: {HELLO_TOPIC} holds a "
                                 f"{type(hello).__name__}, not a Hello")
        self.hello: Hello = hello
        if summary is not None and summary.statistics is not None:
            ids = [c.id for c in summary.channels.values() if c.topic == FRAME_TOPIC]
            self.num_frames = sum(summary.statistics.channel_message_counts.get(i, 0)
                                  for i in ids)
        else:
            self.num_frames = sum(1 for _ in self.frames())

    def _reader(self, f):
        from mcap.reader import make_reader

        try:
            return make_reader(f)
        except Exception as exc:  # noqa: BLE001
            raise RecordingError(f"{self.path}: not an MCAP file ({type(exc).__name__}: "
                                 f"{exc})") from None

    def frames(self) -> Iterator[tuple[int, list[bytes]]]:
        """(log_time_ns, parts) of every recorded Frame, in file order."""
        with open(self.path, "rb") as f:
            reader = self._reader(f)
            try:
                for _, _, message in reader.iter_messages(topics=[FRAME_TOPIC],
                                                          log_time_order=False):
                    yield message.log_time, _unpack_parts(message.data,
                                                          f"{self.path} {FRAME_TOPIC}")
            except RecordingError:
                raise
            except Exception as exc:  # noqa: BLE001
                raise RecordingError(f"{self.path}: corrupt MCAP data ({type(exc).__name__}: "
                                     f"{exc})") from None


def open_recording_source(path: str | Path, max_frames: int | None = None):
    """A capture Source replaying a recording: its Frames are sent exactly as recorded."""
    from arlight.client.capture import Source, SourceFrame

    recording = Recording(path)
    config = recording.hello.config
    n = recording.num_frames if max_frames is None else min(max_frames, recording.num_frames)

    def iterate() -> Iterator[SourceFrame]:
        for i, (log_ns, parts) in enumerate(recording.frames()):
            if i >= n:
                return
            yield SourceFrame(timestamp=log_ns * 1e-9, parts=parts)

    name = config.session if config.session else recording.path.stem
    return Source(name, config.calibration, config.depth_scale, n, iterate,
                  [f"recording of session {config.session!r}: {recording.num_frames} frames"],
                  recorded_config=config)


def record(source, path: str | Path, options, on_frame=None) -> tuple[int, str]:
    """Write `source` to an MCAP file as `arlight stream` would send it (no server needed).

    options: a capture StreamOptions (session name, mode, codecs, preset, timestamps...).
    log_time of each frame is its timestamp. Returns (frames written, session name).
    """
    from arlight.client.capture import CaptureClient, encoded_frames

    client = CaptureClient(source, options)  # only builds the Hello; connects nowhere
    timestamps = options.timestamps or "source"
    with Recorder(path, source=source.name, depth_scale=source.depth_scale) as recorder:
        first_ns = None
        for seq, _, parts in encoded_frames(source, options, timestamps):
            stamp_ns = int(round(float(peek_header(parts)["timestamp"]) * 1e9))
            if first_ns is None:
                first_ns = stamp_ns
                recorder.write_hello(encode(client.hello), stamp_ns)
            recorder.write_frame(parts, None)
            if on_frame is not None:
                on_frame(seq, parts)
        return recorder.frames, client.session
