"""The I/O thread's bookkeeping of peers and sessions: detaching a peer, closing a session
(its Pipeline freed), expiring silent peers and idle sessions, the periodic rate lines.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from arlight.protocols import Bye, ByeKind, encode
from arlight.server.session import Session
from arlight.server.state import Peer

if TYPE_CHECKING:
    from arlight.server.server import Server

log = logging.getLogger("arlight.server.server")  # the server's logger: its lines keep their name


def detach_peer(server: Server, peer: Peer, reason: str) -> None:
    server.peers.pop(peer.identity, None)
    if peer.role == "display":
        subscribers = server.displays.get(peer.session)
        if subscribers is not None:
            subscribers.discard(peer.identity)
            if not subscribers:
                del server.displays[peer.session]
    else:
        session = server.sessions.get(peer.session)
        if session is not None and session.capture_peer == peer.identity:
            session.capture_peer = None
    if peer.results_dropped:
        log.info(
            "session %s: %s lost %d results to a full queue",
            peer.session,
            peer.label,
            peer.results_dropped,
        )
    log.debug("session %s: %s detached (%s)", peer.session, peer.label, reason)


def close_session(server: Server, session: Session, reason: str) -> None:
    """Forget a session (its Pipeline is freed); displays get Bye at the end of a stream."""
    if server.sessions.get(session.name) is session:
        del server.sessions[session.name]
    server.scheduler.remove(session)
    server.stats.sessions_closed += 1
    release = getattr(server._process, "release", None)  # `serve --ray`: the session's actor
    if release is not None:
        try:
            release(session)
        except Exception:  # noqa: BLE001 - the session is gone either way
            log.exception("session %s: failed to release its pipeline", session.name)
    c = session.counters()
    log.info(
        "session %s: closed (%s): %d received, %d processed, %d dropped, %d failed",
        session.name,
        reason,
        c["frames_received"],
        c["frames_processed"],
        c["frames_dropped"],
        c["frames_failed"],
    )
    if session.capture_peer is not None and session.capture_peer in server.peers:
        detach_peer(server, server.peers[session.capture_peer], reason=reason)
    if reason == "end of stream":
        parts = encode(Bye(f"session {session.name} ended", ByeKind.END_OF_STREAM))
        from arlight.server.admission import watchers  # admission imports this module

        for identity in watchers(server, session):
            server._send(identity, parts)


def expire_peers(server: Server, now: float) -> None:
    limit = server.options.liveness * server.options.heartbeat_interval_s
    for peer in list(server.peers.values()):
        if now - peer.last_seen > limit:
            server.stats.peers_expired += 1
            log.warning(
                "session %s: %s silent for %.1f s: declared dead",
                peer.session,
                peer.label,
                now - peer.last_seen,
            )
            detach_peer(server, peer, reason="dead")


def expire_sessions(server: Server, now: float) -> None:
    for session in list(server.sessions.values()):
        if session.idle and now - session.last_activity > server.options.session_timeout_s:
            server.stats.sessions_expired += 1
            close_session(server, session, f"idle for {now - session.last_activity:.0f} s")


def log_rates(server: Server, now: float, interval_s: float) -> None:
    for session in list(server.sessions.values()):
        line = session.rate_line(now, interval_s, len(server.displays.get(session.name, ())))
        if line is not None:
            log.info("%s", line)
