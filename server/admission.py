"""Who may enter which session (section 3 of protocols/SPEC.md, "Handshake"): session tokens
for displays and capture peers, and the session a capture Hello resumes or creates.

Security: docs/guides/security.md. Each function runs on the I/O thread and sends the Error
that refuses a peer itself.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from arlight.protocols import Error, SessionConfig, new_token
from arlight.server.housekeeping import close_session, detach_peer
from arlight.server.security import tokens_equal, unauthorized_error
from arlight.server.session import Session, SessionSetupError

if TYPE_CHECKING:
    from arlight.server.server import Server

log = logging.getLogger("arlight.server.server")  # the server's logger: its lines keep their name


def may_enter(server: Server, token: str | None, session: Session | None) -> bool:
    """The token admits to `session` (None: any, checked again when it is created)."""
    if not server.options.session_tokens or tokens_equal(token, server.admin_token):
        return True
    return tokens_equal(token, session.token) if session is not None else token is not None


def refuse_unauthorized(server: Server, identity: bytes, name: str, role: str) -> None:
    server._send_error(identity, unauthorized_error(name, role))


def display_admitted(server: Server, identity: bytes, cfg: SessionConfig) -> bool:
    """A display Hello: refused (unauthorized) without a token; with one it is subscribed to
    the name whether a session of that name exists or not, and whether the token admits it
    or not, so the answer tells a peer without the token nothing about the name (issue 39,
    item 3); it receives the Results of a session of that name its token admits
    (`watchers`)."""
    if not server.options.session_tokens or cfg.token is not None:
        return True
    refuse_unauthorized(server, identity, cfg.session, "display")
    return False


def watchers(server: Server, session: Session) -> list[bytes]:
    """The displays subscribed to `session`'s name whose token admits it: the peers its
    Results (and its end-of-stream Bye) go to. The others wait, told nothing."""
    out = []
    for identity in list(server.displays.get(session.name, ())):
        peer = server.peers.get(identity)
        if peer is not None and may_enter(server, peer.token, session):
            out.append(identity)
    return out


def capture_session(
    server: Server, identity: bytes, cfg: SessionConfig, client: str = ""
) -> Session | None:
    """The session a capture Hello resumes or creates (section 3 of SPEC.md, "Handshake");
    None after sending the Error that refuses it. client: who asks (server/clients.py), at
    most `max_sessions_per_client` sessions each."""
    name = cfg.session
    session = server.sessions.get(name)
    if session is not None and not may_enter(server, cfg.token, session):
        refuse_unauthorized(server, identity, name, "capture")
        return None
    if session is not None and not session.same_setup(cfg):
        owner = server.peers.get(session.capture_peer) if session.capture_peer else None
        if owner is not None:
            server._send_error(
                identity,
                Error(
                    code="bad_state",
                    field="hello.config.session",
                    message=f"session {name!r} is in use by another capture client with a "
                    "different configuration; choose another session name (--session)",
                ),
            )
            return None
        close_session(server, session, "replaced by a new configuration")
        session = None
    if session is not None:
        previous = session.capture_peer
        if previous is not None and previous != identity and previous in server.peers:
            detach_peer(server, server.peers[previous], reason="replaced by a reconnect")
        log.info(
            "session %s: capture peer %s resumed it (last seq %d)",
            name,
            identity.hex(),
            session.queue.highest_seq,
        )
        return session
    limit = server.options.max_sessions_per_client
    held = sum(1 for s in server.sessions.values() if s.client == client)
    if held >= limit:
        server._send_error(
            identity,
            Error(
                code="too_large",
                field="hello.config.session",
                message=f"this client already holds {held} sessions (limit {limit} per "
                "client, `arlight serve --max-sessions-per-client`); end one (Bye) or let "
                "it expire",
            ),
        )
        return None
    if len(server.sessions) >= server.options.max_sessions:
        server._send_error(
            identity,
            Error(
                code="too_large",
                field="hello.config.session",
                message=f"the server already holds {len(server.sessions)} sessions "
                f"(limit {server.options.max_sessions}, `arlight serve --max-sessions`); "
                "try again later",
            ),
        )
        return None
    try:
        session = Session(
            cfg,
            credits=server.options.credits,
            max_pixels=server.options.max_pixels,
            max_message_bytes=server.options.max_message_bytes,
            process=server._process,
            budget=server.budget,
            cancel=server._cancel,
        )
    except SessionSetupError as exc:
        server._send_error(
            identity, Error(code=exc.code, field=f"hello.config.{exc.field}", message=str(exc))
        )
        return None
    # the client's own token, or one the server makes (never the admin token: the Welcome
    # tells it, and whoever learns a session's token should learn no more than that)
    session.token = (
        cfg.token if cfg.token and not tokens_equal(cfg.token, server.admin_token) else new_token()
    )
    session.client = client
    server.sessions[name] = session
    size = (
        "panorama only"
        if session.camera is None
        else f"{session.camera.width}x{session.camera.height}"
    )
    log.info(
        "session %s: created (%s, %s, preset %s, %d virtual objects) by capture peer %s %s",
        name,
        cfg.mode,
        size,
        cfg.preset,
        len(session.scene.objects) if session.scene else 0,
        identity.hex(),
        repr(cfg.client_name) if cfg.client_name else "",
    )
    return session
