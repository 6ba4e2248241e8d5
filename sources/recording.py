"""Stream recordings in MCAP, the robotics field's log container (https://mcap.dev): the
format and its reader, `Recording` (`arlight.sources.source.open_recording_source` replays
one). The writer is the capture client's (`arlight.client.recording`: `Recorder`, `record`).

One file holds one stream exactly as a capture client sends it:
- channel `/arlight/hello`, message encoding `msgpack`: the session's Hello;
- channel `/arlight/frame`, message encoding `msgpack`: every Frame;
- channel `/arlight/frame_info`, message encoding `json` with a JSON Schema: seq, timestamp,
  codecs and sizes of each frame (Foxglove plots it);
- the Foxglove channels (`/camera/*`, `/tf`, and with Results `/arlight/composite`,
  `/arlight/light`, `/arlight/lighting`; client/foxglove_messages.py) and `/arlight/result`
  (Results as received, msgpack), which this reader ignores;
- a metadata record `arlight` (versions, source, depth scale).

The data of a `msgpack` message is a msgpack array of the ZeroMQ message parts as sent
(each a bin; the first is the protocol's msgpack header, the rest image payloads), so
`arlight stream FILE.mcap` sends the recorded bytes unchanged: a bit-exact replay. The depth
in those frames is the source's uint16 with the recorded Hello's depth_scale.
log_time: when the frame was sent (`stream --record`) or, for an offline `arlight record`,
its timestamp; replay at `--rate native` follows the log_time spacing. publish_time: the
frame's own timestamp. Both in nanoseconds.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import msgpack

from arlight.protocols import Hello, ProtocolError, decode

HELLO_TOPIC = "/arlight/hello"
FRAME_TOPIC = "/arlight/frame"
INFO_TOPIC = "/arlight/frame_info"
RESULT_TOPIC = "/arlight/result"  # Results as received (display and stream --record)
MESSAGE_ENCODING = "msgpack"
PROFILE = "arlight"
MAX_PARTS = 16


class RecordingError(ValueError):
    """An MCAP file that is not a readable arlight recording; the message says why."""


def unpack_parts(data: bytes, where: str) -> list[bytes]:
    """The message parts of one recorded `msgpack` message; RecordingError naming `where`."""
    try:
        parts = msgpack.unpackb(data, raw=False)
    except Exception as exc:  # msgpack raises many types for bad input
        raise RecordingError(f"{where}: message is not msgpack ({type(exc).__name__})") from None
    if (
        not isinstance(parts, list)
        or not 1 <= len(parts) <= MAX_PARTS
        or not all(isinstance(p, bytes) for p in parts)
    ):
        raise RecordingError(f"{where}: expected a msgpack array of 1..{MAX_PARTS} binary parts")
    return parts


class Recording:
    """A recording opened for reading: the Hello, and the frames in file order (lazily)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(
                f"{self.path}: no such file; record one with "
                "`arlight record SOURCE --out FILE.mcap`"
            )
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
                    self.hello_parts = unpack_parts(message.data, f"{self.path} {HELLO_TOPIC}")
                    break
            except RecordingError:
                raise
            except Exception as exc:  # mcap raises many types for corrupt files
                raise RecordingError(
                    f"{self.path}: not a readable MCAP file ({type(exc).__name__}: {exc})"
                ) from None
        if self.hello_parts is None and self.metadata.get("content") == "results":
            raise RecordingError(
                f"{self.path}: a display's recording (`arlight display "
                "--record`) holds Results, no frames to replay; open it in "
                "Foxglove, or replay a capture-side recording (`arlight "
                "record`, `arlight stream --record`)"
            )
        if self.hello_parts is None:
            raise RecordingError(
                f"{self.path}: no {HELLO_TOPIC} message; this is not an "
                "arlight recording (make one with `arlight record`)"
            )
        try:
            hello = decode(self.hello_parts)
        except ProtocolError as exc:
            raise RecordingError(
                f"{self.path}: the recorded Hello does not decode: {exc}"
            ) from None
        if not isinstance(hello, Hello):
            raise RecordingError(
                f"{self.path}: {HELLO_TOPIC} holds a {type(hello).__name__}, not a Hello"
            )
        self.hello: Hello = hello
        if summary is not None and summary.statistics is not None:
            ids = [c.id for c in summary.channels.values() if c.topic == FRAME_TOPIC]
            self.num_frames = sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)
        else:
            self.num_frames = sum(1 for _ in self.frames())

    def _reader(self, f):
        from mcap.reader import make_reader

        try:
            return make_reader(f)
        except Exception as exc:  # noqa: BLE001
            raise RecordingError(
                f"{self.path}: not an MCAP file ({type(exc).__name__}: {exc})"
            ) from None

    def frames(self) -> Iterator[tuple[int, list[bytes]]]:
        """(log_time_ns, parts) of every recorded Frame, in file order."""
        with open(self.path, "rb") as f:
            reader = self._reader(f)
            try:
                for _, _, message in reader.iter_messages(
                    topics=[FRAME_TOPIC], log_time_order=False
                ):
                    yield message.log_time, unpack_parts(message.data, f"{self.path} {FRAME_TOPIC}")
            except RecordingError:
                raise
            except Exception as exc:  # noqa: BLE001
                raise RecordingError(
                    f"{self.path}: corrupt MCAP data ({type(exc).__name__}: {exc})"
                ) from None
