"""A length-prefixed container of multipart messages (golden vectors, simple recordings).

Layout (all integers little-endian; SPEC.md section "Container"):

    file    = magic b"ARLWIRE1" (8 bytes), then records until the end of the file
    record  = u32 part count (1..16), then for each part: u32 byte length, the bytes

The file holds no other framing: a reader that reaches the end in the middle of a record
raises ProtocolError("malformed").
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence

from .codecs import as_bytes_view
from .errors import ProtocolError

CONTAINER_MAGIC = b"ARLWIRE1"
_MAX_PARTS = 16


def write_container(messages: Iterable[Sequence]) -> bytes:
    """Bytes of a container holding the given multipart messages (as from encode())."""
    out = [CONTAINER_MAGIC]
    for parts in messages:
        views = [as_bytes_view(p) for p in parts]
        if not 1 <= len(views) <= _MAX_PARTS:
            raise ProtocolError("malformed", f"{len(views)} parts, expected 1..{_MAX_PARTS}")
        out.append(struct.pack("<I", len(views)))
        for v in views:
            out.append(struct.pack("<I", len(v)))
            out.append(bytes(v))
    return b"".join(out)


def read_container(data) -> list[list[memoryview]]:
    """The multipart messages of a container, as zero-copy views into ``data``."""
    mv = as_bytes_view(data)
    n = len(mv)
    if n < 8 or bytes(mv[:8]) != CONTAINER_MAGIC:
        raise ProtocolError("malformed", "not an arlight container (magic ARLWIRE1 missing)")
    pos = 8
    messages = []
    while pos < n:
        if pos + 4 > n:
            raise ProtocolError("malformed", f"truncated record at byte {pos}")
        (count,) = struct.unpack_from("<I", mv, pos)
        pos += 4
        if not 1 <= count <= _MAX_PARTS:
            raise ProtocolError("malformed", f"record of {count} parts at byte {pos - 4}")
        parts = []
        for _ in range(count):
            if pos + 4 > n:
                raise ProtocolError("malformed", f"truncated record at byte {pos}")
            (length,) = struct.unpack_from("<I", mv, pos)
            pos += 4
            if pos + length > n:
                raise ProtocolError(
                    "malformed", f"part of {length} bytes at byte {pos} runs past the end"
                )
            parts.append(mv[pos : pos + length])
            pos += length
        messages.append(parts)
    return messages
