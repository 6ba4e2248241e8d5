"""The one DEALER socket a client (capture or display) keeps to the server.

Both clients open it the same way (LINGER 0, so a reconnect or exit never waits on unsent
messages; queue limits counted in messages) and read the server's messages the same way
(poll with a timeout in seconds, decode, stamp with the receive time on both clocks).

With CURVE keys (protocols/curve.py, docs/guides/security.md) the socket encrypts everything and
authenticates both ends. A failed handshake (the server wants keys, does not know this
client's key, or is not the server the key names) never reaches the protocol: the socket
monitor reports it, and `receive_message` raises the client's error with what to do.
"""

from __future__ import annotations

import itertools
import logging
import time
from typing import NamedTuple

import zmq
from zmq.utils.monitor import parse_monitor_message

from arlight.protocols import Message, ProtocolError, decode, peek_header
from arlight.protocols.curve import ClientKeys

_HANDSHAKE_EVENTS = (
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
    | zmq.EVENT_HANDSHAKE_SUCCEEDED
)
# failures without detail in a row before a client gives up: a connection that drops during
# the handshake (a restarting server, a network cut) reports the same event, once; a server
# that refuses the mechanism may hang up before the client reads why, again and again
NO_DETAIL_FAILURES = 3
_monitor_ids = itertools.count()


class Dealer(zmq.Socket):
    """A DEALER that watches its own handshakes (a socket monitor on an inproc PAIR)."""

    monitor_socket: zmq.Socket | None = None
    curve: bool = False  # CURVE keys were given
    error_type: type[Exception] = RuntimeError
    no_detail_failures: int = 0  # since the last successful handshake

    def watch_handshakes(self) -> None:
        address = f"inproc://arlight-dealer-monitor-{next(_monitor_ids)}"
        self.monitor(address, _HANDSHAKE_EVENTS)
        pair = self.context.socket(zmq.PAIR)
        pair.setsockopt(zmq.LINGER, 0)
        pair.connect(address)
        self.monitor_socket = pair

    def handshake_failure(self) -> str | None:
        """Why the handshakes with the server fail, once that is certain, else None: the
        server refused the key (ZAP), a plain client met a keyed server (mechanism
        mismatch), a peer that does not speak ZMTP, or failures without detail in a row."""
        pair = self.monitor_socket
        while pair is not None and pair.poll(0):
            message = parse_monitor_message(pair.recv_multipart())
            event, value = message["event"], message["value"]
            if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self.no_detail_failures = 0
            elif event == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
                return (
                    "the server refused this client's key: its public key (--client-key "
                    "NAME.key_secret) is not in the server's authorized/ folder; add it "
                    "with `arlight keys add DIR NAME` on the server and restart it"
                )
            elif event == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
                if value == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH:
                    return (
                        "the handshake failed: the server wants CURVE keys (give "
                        "--server-key DIR/server.key --client-key DIR/client.key_secret)"
                        if not self.curve
                        else "the handshake failed: the server runs "
                        "without keys (drop --server-key/--client-key, or run `arlight "
                        "serve --keys DIR`)"
                    )
                return (
                    "the handshake failed: the peer at this address does not speak the "
                    "arlight protocol as this client does (check --server, and "
                    "--server-key/--client-key against `arlight serve --keys`)"
                )
            else:  # no detail (the peer hung up): count, a single one may be a dropped link
                self.no_detail_failures += 1
                if self.no_detail_failures >= NO_DETAIL_FAILURES:
                    return f"the handshake failed {self.no_detail_failures} times in a row: " + (
                        "--server-key is not the key of the server at this address, "
                        "or that server runs without keys (then drop "
                        "--server-key/--client-key)"
                        if self.curve
                        else "the server probably wants CURVE keys (give --server-key "
                        "DIR/server.key --client-key DIR/client.key_secret)"
                    )
        return None

    def close(self, linger: int | None = None) -> None:
        if self.monitor_socket is not None and not self.closed:
            self.disable_monitor()
            self.monitor_socket.close(linger=0)
            self.monitor_socket = None
        super().close(linger=linger)


class Received(NamedTuple):
    """A message from the server (or the ProtocolError of one that did not decode) and when
    it came: wall clock (for records and latencies against the sender's timestamps) and
    monotonic (for liveness and durations)."""

    message: Message | ProtocolError
    receive_time_wall: float  # time.time(), seconds
    receive_time_mono: float  # time.monotonic(), seconds
    parts: tuple = ()  # the message's parts as received (buffers), for recorders


def open_dealer(
    context: zmq.Context,
    server: str,
    *,
    rcvhwm: int,
    sndhwm: int | None = None,
    error: type[Exception] = RuntimeError,
    keys: ClientKeys | None = None,
) -> Dealer:
    """A DEALER connected to `server`, LINGER 0; rcvhwm/sndhwm: queue limits in messages
    (sndhwm None: ZeroMQ's default); keys: CURVE keys (None: plain TCP). Raises `error` when
    the address is not usable (and, from receive_message, when a handshake fails)."""
    sock = context.socket(zmq.DEALER, socket_class=Dealer)
    sock.error_type = error
    sock.curve = keys is not None
    sock.setsockopt(zmq.LINGER, 0)
    if keys is not None:
        keys.apply(sock)
    sock.watch_handshakes()
    if sndhwm is not None:
        sock.setsockopt(zmq.SNDHWM, sndhwm)
    sock.setsockopt(zmq.RCVHWM, rcvhwm)
    try:
        sock.connect(server)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise error(
            f"cannot connect to {server!r}: {exc}; --server expects tcp://HOST:PORT"
        ) from None
    return sock


def receive_message(sock: zmq.Socket, timeout_s: float, log: logging.Logger) -> Received | None:
    """The next message within timeout_s seconds, or None. An undecodable message is logged
    to `log` and returned as its ProtocolError, with its receive times (the caller decides
    whether it counts as a sign of life). A Dealer whose handshake failed raises its
    error_type instead."""
    if not sock.poll(max(0, int(timeout_s * 1000)), zmq.POLLIN):
        if isinstance(sock, Dealer):
            failure = sock.handshake_failure()
            if failure is not None:
                raise sock.error_type(f"cannot talk to the server: {failure}")
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
    if fmt not in ("jpeg", "png") or not isinstance(index, int) or not 0 <= index < len(parts) - 1:
        return None
    return fmt, bytes(parts[1 + index])
