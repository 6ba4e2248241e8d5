"""Writing stream recordings: `Recorder` (one MCAP file per stream) and `record` (a source
written as `arlight stream` would send it, no server needed).

The format, and its reader, are arlight.sources.recording: one MCAP file, the Hello on
`/arlight/hello`, every Frame exactly as sent on `/arlight/frame` (msgpack arrays of the
ZeroMQ message parts; the bit-exact replay reads these), a JSON `/arlight/frame_info`
channel and an `arlight` metadata record. Beside them, for Foxglove and the `mcap` CLI,
the same stream in Foxglove's own schemas (client/foxglove_messages.py): `/camera/color`,
`/camera/depth`, `/camera/calibration`, `/tf`; and, where the recorder sees Results
(`arlight stream --record`, `arlight display --record`), `/arlight/composite`,
`/arlight/light` and the JSON `/arlight/lighting`, plus, from a display (which keeps the
message parts), each Result as received on `/arlight/result` (msgpack parts).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import msgpack

from arlight import __version__
from arlight.client.capture import CaptureClient, encoded_frames
from arlight.client.foxglove_sinks import FoxgloveStream, McapSink
from arlight.client.stop_signals import uninterrupted
from arlight.protocols import PROTOCOL_VERSION, encode, peek_header
from arlight.sources.recording import (
    FRAME_TOPIC,
    HELLO_TOPIC,
    INFO_TOPIC,
    MESSAGE_ENCODING,
    PROFILE,
    RESULT_TOPIC,
)

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


def _pack_parts(parts) -> bytes:
    return msgpack.packb([bytes(memoryview(p)) for p in parts], use_bin_type=True)


class Recorder:
    """Writes one stream to an MCAP file. Use as a context manager, or call close().

    foxglove: also write the Foxglove channels (False: only arlight's own, as before).
    frames: register the Hello, Frame and frame-info channels (False: a display's recording,
    Results only; write_hello / write_frame then refuse).
    """

    def __init__(
        self,
        path: str | Path,
        source: str = "",
        depth_scale: float | None = None,
        foxglove: bool = True,
        frames: bool = True,
    ):
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=f"arlight {__version__}")
        info_schema = self._writer.register_schema(
            name="arlight.FrameInfo",
            encoding="jsonschema",
            data=json.dumps(FRAME_INFO_SCHEMA).encode(),
        )
        meta = {
            "protocol_version": str(PROTOCOL_VERSION),
            "data": "msgpack array of the ZeroMQ message parts as sent",
        }
        # the channels of a stream recording (frames=True), else None
        self._hello: int | None = None
        self._frame: int | None = None
        self._info: int | None = None
        if frames:
            self._hello = self._writer.register_channel(HELLO_TOPIC, MESSAGE_ENCODING, 0, meta)
            self._frame = self._writer.register_channel(FRAME_TOPIC, MESSAGE_ENCODING, 0, meta)
            self._info = self._writer.register_channel(INFO_TOPIC, "json", info_schema)
        self._result: int | None = None
        self._meta = meta
        self._foxglove = FoxgloveStream(McapSink(self._writer)) if foxglove else None
        self._writer.add_metadata(
            "arlight",
            {
                "arlight_version": __version__,
                "protocol_version": str(PROTOCOL_VERSION),
                "source": source,
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "content": "stream" if frames else "results",
                "depth_scale": "" if depth_scale is None else repr(float(depth_scale)),
            },
        )
        self.frames = 0
        self.results = 0
        self._closed = False

    def write_hello(self, parts, log_time_ns: int) -> None:
        if self._hello is None:
            raise ValueError("this Recorder records Results only (frames=False)")
        with uninterrupted():
            self._write_hello(parts, log_time_ns, self._hello)

    def _write_hello(self, parts, log_time_ns: int, hello: int) -> None:
        self._writer.add_message(
            hello,
            log_time=log_time_ns,
            data=_pack_parts(parts),
            publish_time=log_time_ns,
            sequence=0,
        )
        if self._foxglove is not None:
            self._foxglove.write_hello(parts, log_time_ns)

    def write_frame(self, parts, log_time_ns: int | None = None) -> None:
        """One Frame as sent; log_time_ns None = the frame's own timestamp."""
        if self._frame is None or self._info is None:
            raise ValueError("this Recorder records Results only (frames=False)")
        with uninterrupted():
            self._write_frame(parts, log_time_ns, self._frame, self._info)

    def _write_frame(self, parts, log_time_ns: int | None, frame: int, info_channel: int) -> None:
        header = peek_header(parts)
        stamp_ns = int(round(float(header["timestamp"]) * 1e9))
        log_ns = stamp_ns if log_time_ns is None else int(log_time_ns)
        self._writer.add_message(
            frame,
            log_time=log_ns,
            data=_pack_parts(parts),
            publish_time=stamp_ns,
            sequence=self.frames,
        )
        color, depth = header.get("color") or {}, header.get("depth") or {}
        info = {
            "seq": header["seq"],
            "timestamp": header["timestamp"],
            "color_codec": color.get("format", ""),
            "depth_codec": depth.get("format", ""),
            "width": color.get("width", 0),
            "height": color.get("height", 0),
            "bytes": sum(len(memoryview(p)) for p in parts),
            "has_pose": header.get("pose") is not None,
        }
        self._writer.add_message(
            info_channel,
            log_time=log_ns,
            data=json.dumps(info).encode(),
            publish_time=stamp_ns,
            sequence=self.frames,
        )
        self.frames += 1
        if self._foxglove is not None:
            self._foxglove.write_frame(parts, log_ns)

    def write_result(
        self, result, record: dict, parts=None, log_time_ns: int | None = None
    ) -> None:
        """One Result as received: its message parts (when given) on /arlight/result, and
        the Foxglove channels of it. record: protocols.received_record of it; log_time_ns
        None = the receive time."""
        with uninterrupted():
            self._write_result(result, record, parts, log_time_ns)

    def _write_result(self, result, record: dict, parts, log_time_ns: int | None) -> None:
        log_ns = (
            int(round(record["receive_time"] * 1e9)) if log_time_ns is None else int(log_time_ns)
        )
        if parts is not None:
            if self._result is None:
                self._result = self._writer.register_channel(
                    RESULT_TOPIC, MESSAGE_ENCODING, 0, self._meta
                )
            self._writer.add_message(
                self._result,
                log_time=log_ns,
                data=_pack_parts(parts),
                publish_time=int(round(result.timestamp * 1e9)),
                sequence=self.results,
            )
        self.results += 1
        if self._foxglove is not None:
            self._foxglove.write_result(result, record, log_ns, parts=parts)

    def close(self) -> None:
        """Write the summary and footer (a stop signal meanwhile waits for them)."""
        if not self._closed:
            self._closed = True
            with uninterrupted():
                self._writer.finish()
                self._file.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ProcessedRecorder:
    """A Recorder that keeps only the frames the server processed (`stream --record
    --record-processed`): each frame sent waits until its Result comes, then is written with
    it; a frame the server passed over (live mode: it took a newer one) goes when a Result
    of a later frame comes, and is never written. The frames waiting are capped at
    `hold_bytes` (the oldest let go first; a live server answers seconds late, so at 30 fps
    hundreds wait). The recording replays like any other (its seq numbers have gaps).
    Same interface as Recorder."""

    # sizes per minute, whole against processed: docs/results/recordings.md
    def __init__(self, recorder: Recorder, hold_bytes: int = 512 * 2**20):
        self.recorder = recorder
        self.hold_bytes = hold_bytes
        self._waiting: dict[int, tuple[list, int | None]] = {}  # seq -> (parts, log_ns)
        self._waiting_bytes = 0
        self.skipped = 0  # frames sent and never written

    @property
    def frames(self) -> int:
        return self.recorder.frames

    @property
    def path(self) -> Path:
        return self.recorder.path

    def write_hello(self, parts, log_time_ns: int) -> None:
        self.recorder.write_hello(parts, log_time_ns)

    def _let_go(self, seq: int) -> tuple[list, int | None]:
        frame = self._waiting.pop(seq)
        self._waiting_bytes -= sum(len(p) for p in frame[0])
        return frame

    def write_frame(self, parts, log_time_ns: int | None = None) -> None:
        seq = int(peek_header(parts)["seq"])
        kept = [bytes(memoryview(p)) for p in parts]
        self._waiting[seq] = (kept, log_time_ns)
        self._waiting_bytes += sum(len(p) for p in kept)
        while self._waiting_bytes > self.hold_bytes and len(self._waiting) > 1:
            self._let_go(next(iter(self._waiting)))
            self.skipped += 1

    def write_result(self, result, record: dict, parts=None, log_time_ns=None) -> None:
        for seq in [s for s in self._waiting if s < result.seq]:  # passed over by the server
            self._let_go(seq)
            self.skipped += 1
        if result.seq in self._waiting:
            self.recorder.write_frame(*self._let_go(result.seq))
        self.recorder.write_result(result, record, parts, log_time_ns)

    def close(self) -> None:
        self.skipped += len(self._waiting)
        self._waiting.clear()
        self._waiting_bytes = 0
        self.recorder.close()


def record(source, path: str | Path, options, on_frame=None) -> tuple[int, str]:
    """Write `source` to an MCAP file as `arlight stream` would send it (no server needed).

    options: a capture StreamOptions (session name, mode, codecs, preset, timestamps...).
    log_time of each frame is its timestamp. Returns (frames written, session name).
    """
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
