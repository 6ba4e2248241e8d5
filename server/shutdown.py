"""A clean shutdown (`Server.stop()`, SIGINT/SIGTERM in `arlight serve`): the lossless frames
already received are finished within `shutdown_grace_s`, the rest reported with a retryable
Error, every peer told Bye, the socket closed.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import zmq

from arlight.protocols import Bye, ByeKind, Error, ErrorField, encode

if TYPE_CHECKING:
    from arlight.server.server import Server

log = logging.getLogger("arlight.server.server")  # the server's logger: its lines keep their name


def begin_drain(server: Server, now: float) -> None:
    server._draining = True
    server._drain_deadline = now + server.options.shutdown_grace_s
    waiting = 0
    for session in server.sessions.values():
        frames = session.queue
        if frames.lossless:
            waiting += len(frames.pending) + (frames.in_flight is not None)
        else:
            frames.drop_pending()
    log.info(
        "shutting down: %d lossless frame(s) still to finish (grace %g s)",
        waiting,
        server.options.shutdown_grace_s,
    )


def drained(server: Server) -> bool:
    return all(
        s.queue.in_flight is None and not (s.lossless and s.queue.pending)
        for s in server.sessions.values()
    )


def finish_shutdown(server: Server) -> None:
    """Report unfinished lossless frames, say Bye to every peer, close the socket."""
    router = server._socket
    server._cancel.set()  # a frame still in a worker is abandoned at its next stage
    try:
        for session in list(server.sessions.values()):
            in_flight = session.queue.in_flight
            unfinished = [in_flight] if in_flight else []
            unfinished += session.queue.drop_pending()
            if session.capture_peer is not None:
                for job in unfinished:
                    server._send_error(
                        session.capture_peer,
                        Error(
                            code="bad_state",
                            field=ErrorField.SHUTDOWN,
                            seq=job.seq,
                            retryable=True,
                            message="the server shut down before processing this frame; "
                            "send it again after reconnecting",
                        ),
                    )
            if unfinished:
                log.warning(
                    "session %s: %d frame(s) not processed at shutdown (reported to the client)",
                    session.name,
                    len(unfinished),
                )
        bye = encode(Bye("server shutting down", ByeKind.SHUTDOWN))
        for identity in list(server.peers):
            server._send(identity, bye)
        router.setsockopt(zmq.LINGER, 1000)  # let the Byes and last Results out
    except Exception:  # noqa: BLE001
        log.exception("error while shutting down")
    finally:
        router.close()
        if server._executor is not None:
            server._executor.shutdown(wait=False, cancel_futures=True)
        server._stop_curve()
        if server._ctx is not None:
            server._ctx.term()
        server._wake_r.close()
        server._wake_w.close()
        server.sessions.clear()
        log.info("server stopped")
