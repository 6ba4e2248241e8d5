"""The wire framing (SPEC.md sections 2 and 3): a message is a ZeroMQ multipart message
``[header, buffer 0, buffer 1, ...]``; encode() and decode() turn messages into parts and back.

The header is a msgpack map with ``"v"`` (protocol version), ``"type"`` and the message's
fields; every image is described in the header and travels as its own part, so raw numpy
buffers go out zero-copy. ``"buffers"`` lists each part's byte length.

decode() is strict: any input, however hostile, either gives a valid message or raises
ProtocolError naming the field; sizes are checked against the limits before anything is
allocated. encode() runs the same header checks, so a peer never sends what it would reject.
Each message class owns its bytes (as mcap's records.py): `_pack(parts)` gives its header
fields in SPEC.md's key order, `_unpack(h, v, images)` reads and checks them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Union

import msgpack

from .codecs import DEFAULT_MAX_PIXELS, as_bytes_view
from .control import Bye, Credit, Error, Heartbeat, Welcome
from .errors import ProtocolError
from .fields import (
    DEFAULT_MAX_MESSAGE_BYTES,
    MAX_HEADER_BYTES,
    MAX_PARTS,
    PROTOCOL_VERSION,
    FieldReader,
    to_plain,
    type_name,
)
from .frame_result import Frame, Result
from .images import ImageParts
from .session_config import Hello

Message = Union[Hello, Welcome, Frame, Result, Credit, Error, Heartbeat, Bye]  # noqa: UP007
MessageClass = Union[  # noqa: UP007
    type[Hello],
    type[Welcome],
    type[Frame],
    type[Result],
    type[Credit],
    type[Error],
    type[Heartbeat],
    type[Bye],
]

MESSAGE_TYPES: dict[str, MessageClass] = {
    cls.TYPE: cls for cls in (Hello, Welcome, Frame, Result, Credit, Error, Heartbeat, Bye)
}
_TYPE_NAMES = {cls: name for name, cls in MESSAGE_TYPES.items()}


def encode(
    msg: Message,
    *,
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_pixels: int = DEFAULT_MAX_PIXELS,
) -> list[bytes | memoryview]:
    """Multipart ZeroMQ frames ``[msgpack header, buffer 0, ...]``; raw images zero-copy.

    Raises ProtocolError (``bad_field``, ``bad_codec``, ``too_large``) for a message that
    decode() would reject. Send with ``socket.send_multipart(parts, copy=False)``.
    """
    name = _TYPE_NAMES.get(type(msg))
    if name is None:
        raise ProtocolError("unknown_type", f"{type(msg).__name__} is not a protocol message")
    version = msg.protocol_version if isinstance(msg, (Hello, Welcome)) else PROTOCOL_VERSION
    parts: list[bytes | memoryview] = []
    header: dict[str, Any] = {"v": to_plain(version), "type": name}
    header.update(msg._pack(parts))
    if parts:
        header["buffers"] = [len(as_bytes_view(p)) for p in parts]
    if version != PROTOCOL_VERSION:  # a deliberately wrong version (tests); skip the checks
        return [msgpack.packb(header, use_bin_type=True), *parts]
    m = FieldReader(header, name)
    m.seen.update(("v", "type", "buffers"))
    images = ImageParts([as_bytes_view(p) for p in parts], max_pixels, decode=False)
    type(msg)._unpack(m, version, images)
    m.done()
    images.done(name)
    try:
        packed = msgpack.packb(header, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:  # pragma: no cover - checked above
        raise ProtocolError("bad_field", f"cannot pack header: {exc}", name) from None
    total = len(packed) + sum(header.get("buffers", ()))
    if len(packed) > MAX_HEADER_BYTES:
        raise ProtocolError(
            "too_large", f"header of {len(packed)} bytes exceeds {MAX_HEADER_BYTES}", name
        )
    if total > max_message_bytes:
        raise ProtocolError(
            "too_large",
            f"message of {total} bytes exceeds max_message_bytes {max_message_bytes}",
            name,
        )
    return [packed, *parts]


def _views(parts: Any) -> list[memoryview]:
    if isinstance(parts, (bytes, bytearray, memoryview, str)) or not isinstance(parts, Sequence):
        raise ProtocolError("malformed", "expected a sequence of message parts")
    if not parts:
        raise ProtocolError("malformed", "empty multipart message")
    if len(parts) > MAX_PARTS:
        raise ProtocolError("malformed", f"{len(parts)} parts, at most {MAX_PARTS}")
    return [as_bytes_view(p) for p in parts]


# A header's containers (maps and arrays, at every depth) and the longest one. msgpack builds
# every container as a Python object: a 1 MiB header of 2^20 empty arrays cost 0.4-0.8 s to
# parse (the garbage collector's passes over the objects made), on the server's I/O thread
# (issue 39, item 2; figures: docs/reliability.md). A legitimate header holds far fewer: a
# Result's diagnostics at most 4096 values in all, a Hello's scene 64 objects.
MAX_HEADER_CONTAINERS = 16384
MAX_HEADER_ARRAY = 4096  # elements of one array (Result.sh: 1024; diagnostics arrays: 1024)
MAX_HEADER_MAP = 1024  # entries of one map


class _TooManyContainers(Exception):
    """More than MAX_HEADER_CONTAINERS maps and arrays in one header (raised while parsing)."""


class _RepeatedKey(Exception):
    """A msgpack map that names one key twice (raised inside msgpack's unpacker)."""

    def __init__(self, key: Any):
        super().__init__(key)
        self.key = key


class _Counted:
    """msgpack's hooks for one header: each map as a dict refusing a key it names twice
    (SPEC.md section 2: a reader keeping the first value and one keeping the last would see
    different messages), and every map and array counted, parsing stopped past
    MAX_HEADER_CONTAINERS."""

    def __init__(self) -> None:
        self.left = MAX_HEADER_CONTAINERS

    def _count(self) -> None:
        self.left -= 1
        if self.left < 0:
            raise _TooManyContainers

    def map(self, pairs: list[tuple[Any, Any]]) -> dict:
        self._count()
        out = dict(pairs)
        if len(out) != len(pairs):
            seen: set = set()
            for key, _ in pairs:
                if key in seen:
                    raise _RepeatedKey(key)
                seen.add(key)
        return out

    def array(self, items: list) -> list:
        self._count()
        return items


def _header(view: memoryview) -> dict:
    if len(view) > MAX_HEADER_BYTES:
        raise ProtocolError(
            "too_large", f"header of {len(view)} bytes exceeds {MAX_HEADER_BYTES}", "header"
        )
    hooks = _Counted()
    try:
        header = msgpack.unpackb(
            view,
            raw=False,
            strict_map_key=True,
            use_list=True,
            object_pairs_hook=hooks.map,
            list_hook=hooks.array,
            max_array_len=MAX_HEADER_ARRAY,
            max_map_len=MAX_HEADER_MAP,
        )
    except _TooManyContainers:
        raise ProtocolError(
            "too_large",
            f"header holds more than {MAX_HEADER_CONTAINERS} maps and arrays",
            "header",
        ) from None
    except _RepeatedKey as exc:
        raise ProtocolError(
            "malformed",
            f"the key {str(exc.key)[:64]!r} appears twice in one map (every key "
            "of every map exactly once)",
            "header",
        ) from None
    except Exception as exc:  # msgpack raises many types for bad input
        if isinstance(exc, ValueError) and "exceeds max_" in str(exc):
            raise ProtocolError(
                "too_large",
                f"header holds an array over {MAX_HEADER_ARRAY} elements or a map over "
                f"{MAX_HEADER_MAP} entries ({str(exc)[:100]})",
                "header",
            ) from None
        raise ProtocolError(
            "malformed", f"header is not msgpack: {type(exc).__name__}: {str(exc)[:200]}", "header"
        ) from None
    if type(header) is not dict:
        raise ProtocolError(
            "malformed", f"header is a msgpack {type_name(header)}, expected a map", "header"
        )
    v = header.get("v")
    if type(v) is not int:
        raise ProtocolError(
            "malformed",
            f"header field v (protocol version) is {type_name(v)}, expected an integer",
            "v",
        )
    if v != PROTOCOL_VERSION:
        raise ProtocolError(
            "bad_version", f"protocol version {v}, this peer speaks {PROTOCOL_VERSION}", "v"
        )
    t = header.get("type")
    if type(t) is not str:
        raise ProtocolError(
            "malformed", f"header field type is {type_name(t)}, expected a string", "type"
        )
    if t not in MESSAGE_TYPES:
        raise ProtocolError(
            "unknown_type", f"message type {t[:64]!r} is not one of {tuple(MESSAGE_TYPES)}", "type"
        )
    return header


def peek_header(parts: Any) -> dict:
    """The msgpack header (a map with a valid "v" and "type"), without decoding any image."""
    return _header(_views(parts)[0])


def decode(
    parts: Sequence[Any],
    *,
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    header: dict | None = None,
) -> Message:
    """Decode a multipart message; raises ProtocolError (never anything else) naming the field.
    header: what peek_header(parts) returned (its checks done), so the header is parsed once;
    the decoded message may share its lists."""
    try:
        return _decode(parts, max_message_bytes, max_pixels, header)
    except ProtocolError:
        raise
    except Exception as exc:  # a bug or an input we did not foresee: still a ProtocolError
        raise ProtocolError("malformed", f"{type(exc).__name__}: {str(exc)[:200]}") from exc


def _decode(parts: Any, max_message_bytes: int, max_pixels: int, header: dict | None) -> Message:
    views = _views(parts)
    total = sum(len(p) for p in views)
    if total > max_message_bytes:
        raise ProtocolError(
            "too_large", f"message of {total} bytes exceeds max_message_bytes {max_message_bytes}"
        )
    if header is None:
        header = _header(views[0])
    name = header["type"]
    bufs = views[1:]
    declared = header.get("buffers", [])
    if type(declared) is not list or any(type(n) is not int for n in declared):
        raise ProtocolError(
            "malformed", "buffers must be an array of byte lengths", f"{name}.buffers"
        )
    if len(declared) != len(bufs):
        raise ProtocolError(
            "malformed",
            f"header declares {len(declared)} buffer(s), the "
            f"message has {len(bufs)} part(s) after the header",
            f"{name}.buffers",
        )
    for i, (n, b) in enumerate(zip(declared, bufs, strict=True)):
        if n != len(b):
            raise ProtocolError(
                "malformed",
                f"buffer {i} is {len(b)} bytes, the header declares {n}",
                f"{name}.buffers[{i}]",
            )
    m = FieldReader(header, name)
    m.seen.update(("v", "type", "buffers"))
    images = ImageParts(bufs, max_pixels)
    msg = MESSAGE_TYPES[name]._unpack(m, header["v"], images)
    m.done()
    images.done(name)
    return msg
