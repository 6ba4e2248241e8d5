"""The one DEALER socket a client (capture or display) keeps to the server.

Both clients open it the same way (LINGER 0, so a reconnect or exit never waits on unsent
messages; queue limits counted in messages) and read the server's messages the same way
(poll with a timeout in seconds, decode, stamp with the receive time on both clocks).
"""

from __future__ import annotations

import logging
import time
from typing import NamedTuple

import zmq

from arlight.protocols import ProtocolError, decode, peek_header


class Received(NamedTuple):
    """A message from the server (or the ProtocolError of one that did not decode) and when
    it came: wall clock (for records and latencies against the sender's timestamps) and
    monotonic (for liveness and durations)."""

    message: object
    receive_time_wall: float  # time.time(), seconds
    receive_time_mono: float  # time.monotonic(), seconds
    parts: tuple = ()  # the message's parts as received (buffers), for recorders


def open_dealer(context: zmq.Context, server: str, *, rcvhwm: int, sndhwm: int | None = None,
                error: type[Exception] = RuntimeError) -> zmq.Socket:
    """A DEALER connected to `server`, LINGER 0; rcvhwm/sndhwm: queue limits in messages
    (sndhwm None: ZeroMQ's default). Raises `error` when the address is not usable."""
    sock = context.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    if sndhwm is not None:
        sock.setsockopt(zmq.SNDHWM, sndhwm)
    sock.setsockopt(zmq.RCVHWM, rcvhwm)
    try:
        sock.connect(server)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise error(f"cannot connect to {server!r}: {exc}; --server expects "
                    "tcp://HOST:PORT") from None
    return sock


def receive_message(sock: zmq.Socket, timeout_s: float, log: logging.Logger
                    ) -> Received | None:
    """The next message within timeout_s seconds, or None. An undecodable message is logged
    to `log` and returned as its ProtocolError, with its receive times (the caller decides
    whether it counts as a sign of life)."""
    if not sock.poll(max(0, int(timeout_s * 1000)), zmq.POLLIN):
        return None
    parts = sock.recv_multipart(copy=False)
    wall, mono = time.time(), time.monotonic()
    buffers = tuple(p.buffer for p in parts)
    try:
        return Received(decode(list(buffers)), wall, mono, buffers)
    except ProtocolError as exc:
        log.warning("undecodable message from the server ignored: %s", exc)
        return Received(exc, wall, mono)


def encoded_image(parts, key: str) -> tuple[str, bytes] | None:
    """(format, bytes) of the JPEG or PNG image `key` of a received message (its parts as
    received: the msgpack header, then the buffers), or None (raw, absent, no parts)."""
    if not parts:
        return None
    descriptor = peek_header(parts).get(key) or {}
    index = descriptor.get("buffer")
    fmt = descriptor.get("format")
    if fmt not in ("jpeg", "png") or not isinstance(index, int) \
            or not 0 <= index < len(parts) - 1:
        return None
    return fmt, bytes(parts[1 + index])
