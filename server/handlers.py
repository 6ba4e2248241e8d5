"""Messages from peers, on the I/O thread: each routed by type (server/server.py receives them).

A Frame goes to its session's queue undecoded (server/frame_queue.py); a Hello admits a display
or a capture peer (server/admission.py) and is answered with a Welcome; a Bye detaches its peer.
Every refusal is an Error to the peer; a bad message never stops the server.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    Credit,
    Error,
    ErrorField,
    Heartbeat,
    Hello,
    ProtocolError,
    Welcome,
    decode,
    encode,
    error_from_exception,
    peek_header,
)
from arlight.protocols.fields import MAX_INT as MAX_SEQ  # a Frame's seq: 0..2^63-1
from arlight.server.admission import capture_session, display_admitted
from arlight.server.clients import HELLO_IO_SHARE, HELLO_TRIANGLES_PER_TOKEN, hello_cost
from arlight.server.frame_queue import Job, Offer
from arlight.server.housekeeping import close_session, detach_peer
from arlight.server.logtext import printable
from arlight.server.state import Peer

if TYPE_CHECKING:
    from arlight.server.server import Server

log = logging.getLogger("arlight.server.server")  # the server's logger: its lines keep their name


def handle_message(
    server: Server,
    identity: bytes,
    parts: list,
    now: float,
    receive_time_wall: float,
    client: str = "",
) -> None:
    """One message from a peer; now: time.monotonic(), receive_time_wall: time.time();
    client: who sent it (server/clients.py: its CURVE key or address)."""
    peer = server.peers.get(identity)
    if peer is not None:
        peer.last_seen = now
    if not parts:
        server._send_error(identity, Error(code="malformed", message="empty message"))
        return
    try:
        header = peek_header(parts)
    except ProtocolError as exc:
        server._send_error(identity, error_from_exception(exc))
        return
    if header["type"] == "frame":  # routed undecoded: a worker decodes it, and a
        # live frame replaced in the queue costs no decoding at all
        on_frame(server, identity, peer, header, parts, now, receive_time_wall)
        return
    try:
        message = decode(
            parts,
            max_message_bytes=server.options.max_message_bytes,
            max_pixels=server.options.max_pixels,
            header=header,  # parsed once
        )
    except ProtocolError as exc:
        server._send_error(identity, error_from_exception(exc))
        return
    if isinstance(message, Hello):
        scene = message.config.scene
        triangles = 0 if scene is None else sum(len(o.triangles) for o in scene.objects)
        cost = hello_cost(triangles)
        if not server.hellos.allow(client, now, cost):
            server._send_error(
                identity,
                Error(
                    code="too_large",
                    field="hello",
                    retryable=False,
                    message=f"more than {server.options.hellos_per_client_s:g} Hellos a second "
                    "from this client (`arlight serve --hellos-per-client`; a scene's every "
                    f"{HELLO_TRIANGLES_PER_TOKEN} triangles count as one more, and Hellos may "
                    f"hold the server at most {HELLO_IO_SHARE:.0%} of the time); wait and say "
                    "Hello again",
                ),
            )
            return
        on_hello(server, identity, message, now, client)
        done = time.monotonic()
        server.hellos.settle(client, done, cost, busy_s=done - now)
    elif isinstance(message, Heartbeat):
        if peer is None:  # e.g. after a server restart: tell the client to say Hello again
            server._send_error(
                identity,
                Error(
                    code="bad_state",
                    field=ErrorField.SESSION,
                    retryable=True,
                    message="unknown peer: send Hello first (the server may have restarted)",
                ),
            )
    elif isinstance(message, Bye):
        on_bye(server, identity, peer, message)
    elif isinstance(message, (Credit, Error)):
        if isinstance(message, Error):  # the peer's text, escaped and rate-limited
            server._error_log.reported(identity, message, now)
    else:
        server._send_error(
            identity,
            Error(
                code="bad_state",
                field=ErrorField.TYPE,
                message=f"a client may send Hello, Frame, Heartbeat, Credit or Bye, "
                f"not {type(message).__name__}",
            ),
        )


def on_hello(server: Server, identity: bytes, hello: Hello, now: float, client: str = "") -> None:
    cfg = hello.config
    name = cfg.session  # 1..64 characters of [A-Za-z0-9_.-]: decode() checked it
    old = server.peers.get(identity)
    if old is not None:
        detach_peer(server, old, reason="said Hello again")
    if cfg.role == "display":
        if not display_admitted(server, identity, cfg):
            return  # refused: the Error is sent
        server.peers[identity] = Peer(
            identity, "display", name, cfg.client_name, now, token=cfg.token
        )
        server.displays[name].add(identity)
        log.info("session %s: display peer %s subscribed", name, identity.hex())
        send_welcome(server, identity, name, credits=0)
        return
    if server._draining:
        server._send_error(
            identity,
            Error(
                code="bad_state",
                field=ErrorField.SHUTDOWN,
                retryable=True,
                message="the server is shutting down",
            ),
        )
        return
    session = capture_session(server, identity, cfg, client)
    if session is None:
        return  # refused: the Error is sent
    session.capture_peer = identity
    session.ended = False
    # a Hello does not keep a session alive (only frames do): Hellos every minute held 32
    # sessions without a frame (issue 39, item 3)
    server.peers[identity] = Peer(identity, "capture", name, cfg.client_name, now)
    # the token goes only to a client that sent one (older clients refuse the key)
    send_welcome(
        server,
        identity,
        name,
        credits=server.options.credits,
        token=session.token if cfg.token is not None else None,
    )


def send_welcome(
    server: Server, identity: bytes, session: str, credits: int, token: str | None = None
) -> None:
    server._send(
        identity,
        encode(
            Welcome(
                PROTOCOL_VERSION,
                session,
                credits,
                server.options.heartbeat_interval_s,
                server.options.name,
                token,
            )
        ),
    )


def on_frame(
    server: Server,
    identity: bytes,
    peer: Peer | None,
    header: dict,
    parts: list,
    now: float,
    receive_time_wall: float,
) -> None:
    seq = header.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool) or not 0 <= seq <= MAX_SEQ:
        shown = repr(seq)[:64]
        server._send_error(
            identity,
            Error(
                code="bad_field",
                field="frame.seq",
                message=f"seq must be an integer in 0..2^63-1, got {shown}",
            ),
        )
        return
    session = server.sessions.get(peer.session) if peer is not None else None
    if (
        peer is None
        or peer.role != "capture"
        or session is None
        or session.capture_peer != identity
    ):
        server._send_error(
            identity,
            Error(
                code="bad_state",
                field=ErrorField.SESSION,
                seq=seq,
                retryable=True,
                message="no session for this peer: send Hello first (the server may have "
                "restarted or the session expired)",
            ),
        )
        return
    if server._draining:
        server._send_error(
            identity,
            Error(
                code="bad_state",
                field=ErrorField.SHUTDOWN,
                seq=seq,
                retryable=True,
                message="the server is shutting down; frame not processed",
            ),
        )
        return
    frames = session.queue
    offer = frames.offer(Job(seq, parts, receive_time_wall, now))
    if offer is Offer.RESEND:  # its Result or final Error, again (the first may be lost)
        server._send(identity, frames.reply(seq))
    elif offer is Offer.EXPIRED:  # answer it, or a lossless client would wait forever
        server._send_error(
            identity,
            Error(
                code="bad_state",
                field=ErrorField.DUPLICATE,
                seq=seq,
                retryable=False,
                message=f"frame {seq} is not above the highest seq this session accepted "
                f"({frames.highest_seq}) and its Result or Error is no longer kept "
                f"(only the last {frames.keeps} are); it is not processed again",
            ),
        )
    elif offer is Offer.OVERFLOW:
        server._send_error(
            identity,
            Error(
                code="bad_state",
                field=ErrorField.CREDITS,
                seq=seq,
                retryable=True,
                message=f"more than {server.options.credits} frames (or "
                f"{frames.max_queued_bytes / 2**20:.1f} MiB) unacknowledged in lossless "
                "mode; wait for Results (credits) before sending more",
            ),
        )
    server._schedule(session)


def on_bye(server: Server, identity: bytes, peer: Peer | None, bye: Bye) -> None:
    if peer is None:
        return
    log.info("session %s: %s said Bye (%s)", peer.session, peer.label, printable(bye.reason))
    session = server.sessions.get(peer.session)
    detach_peer(server, peer, reason="said Bye")
    if peer.role == "capture" and session is not None and session.capture_peer is None:
        session.ended = True
        if session.idle:
            close_session(server, session, "end of stream")
