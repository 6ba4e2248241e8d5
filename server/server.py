"""The streaming server: one ZeroMQ ROUTER socket, one I/O thread, a pool of worker threads.

Transport (protocols/SPEC.md): every client, capture or display, talks to the one ROUTER
through a DEALER; the ROUTER prepends the peer's identity frame. Only the I/O thread touches
the socket. It routes frames to their session's queue (server/frame_queue.py), hands at most
one frame per session to the worker pool (so a session's frames stay in order), where
`run_frame` (server/worker.py) processes it, and sends the replies back to the capture peer
and to every display peer subscribed to the session. A worker turns the frame's outcome into
its encoded Result (server/results.py), reports through a queue and wakes the I/O thread
through a socket pair it polls.

This module holds the Server itself: its lifecycle, the I/O loop, the worker pool and the
sending. The I/O thread's other concerns have modules of their own, functions of the Server:
server/handlers.py (each message from a peer), server/admission.py (session tokens, the
session a capture Hello resumes or creates), server/housekeeping.py (detaching peers, closing
and expiring sessions), server/shutdown.py (the drain and the Byes); server/state.py holds
the Peer and ServerStats records.

Limits on everything that crosses the wire (each a ServerOptions field): the largest message
(zmq MAXMSGSIZE drops a connection that sends more, the protocol decoder checks declared
sizes), the largest image, the credit window, the per-peer send queue (SNDHWM: a display that
reads slowly loses Results, counted, and never stalls the pipeline), the number of sessions.

Budgets (server/budget.py): a Hello whose settings could not meet them is refused
(`over_budget`); a frame past the per-frame deadline is abandoned between stages (`deadline`).
Every frame accepted is answered: a worker that fails still hands back an Error for it.

Liveness (zguide's Paranoid Pirate): the server sends a Heartbeat to every peer each
`heartbeat_interval_s`; a peer silent for `liveness` intervals is dead and is detached (its
session survives for a reconnecting client). A session that receives no frames for
`session_timeout_s` expires and frees its Pipeline. `stop()` (SIGINT/SIGTERM in
`arlight serve`) finishes the lossless frames already received within `shutdown_grace_s`,
reports the rest with an Error, says Bye to every peer and closes the socket.

Security (server/security.py, docs/guides/security.md): a loopback bind by default, CURVE keys
(`keys_dir`) for any other; session tokens keep sessions apart.

Clocks: liveness, expiry, the heartbeat schedule and the shutdown deadline run on
time.monotonic(); time.time() is read only for what goes on the wire (Heartbeat.time, a
Result's server receive/finish times).
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import cast

import zmq

from arlight.pipeline.runtime import concurrent_pipelines_safe
from arlight.protocols import Error, ErrorField, Heartbeat, encode, new_token
from arlight.server.admission import watchers
from arlight.server.budget import SessionBudget
from arlight.server.clients import HelloLimiter, client_of
from arlight.server.frame_queue import Job
from arlight.server.handlers import handle_message
from arlight.server.housekeeping import (
    close_session,
    detach_peer,
    expire_peers,
    expire_sessions,
    log_rates,
)
from arlight.server.options import DEFAULT_BIND, ServerOptions
from arlight.server.results import ErrorLog, Reply, encode_error, error_reply, reply_to
from arlight.server.routing import seed_routing_ids
from arlight.server.scheduler import Scheduler
from arlight.server.security import CurveServer, check_exposure
from arlight.server.session import Session
from arlight.server.shutdown import begin_drain, drained, finish_shutdown
from arlight.server.state import Peer, ServerStats
from arlight.server.worker import ProcessStep, run_frame

# importable from here as before the split (tests, the CLI, the benchmarks): run_frame is
# looked up here by the worker threads, so a test may patch it here
__all__ = [
    "DEFAULT_BIND",
    "MAX_MESSAGES_PER_POLL",
    "Peer",
    "Server",
    "ServerOptions",
    "ServerStats",
    "run_frame",
]

log = logging.getLogger(__name__)

MAX_MESSAGES_PER_POLL = 256  # fairness between reading the socket and sending results
MAX_READ_S_PER_POLL = 0.05  # and a time bound: a flood of messages (each refused at a bounded
# cost) never holds back the finished Results for long (issue 39, item 2)


class Server:
    """The streaming service, runnable in-process: `start()`, `endpoint`/`port`, `stop()`.

    process: optional compute step replacing Pipeline.process (tests and the transport
    benchmark only).
    """

    def __init__(self, options: ServerOptions | None = None, process: ProcessStep | None = None):
        self.options = options or ServerOptions()
        self._process = process
        self._remote = bool(getattr(process, "runs_elsewhere", False))  # `serve --ray`
        self.sessions: dict[str, Session] = {}
        self.peers: dict[bytes, Peer] = {}
        self.displays: dict[str, set[bytes]] = collections.defaultdict(set)
        self.stats = ServerStats()
        self.endpoint: str | None = None
        self.port: int | None = None
        self._ctx: zmq.Context | None = None
        self._router: zmq.Socket | None = None
        self._completions: queue.SimpleQueue[Reply] = queue.SimpleQueue()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._stop_requested = threading.Event()
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._compute_lock = threading.Lock()
        self._draining = False
        self._drain_deadline = math.inf
        # admits a display to any session's Results (and a capture Hello to any session)
        self.admin_token = self.options.admin_token or new_token()
        self._curve: CurveServer | None = None
        self._cancel = threading.Event()  # set at the end of a shutdown: workers give up
        self._busy = 0  # jobs in worker threads (under _busy_lock)
        self._busy_lock = threading.Condition()
        self._error_log = ErrorLog()  # Errors sent to peers: a flood is summarised
        self.scheduler = Scheduler(self.options.workers)  # made again at start()
        self.hellos = HelloLimiter(self.options.hellos_per_client_s)
        self.budget = SessionBudget(
            self.options.frame_deadline_s, self.options.session_memory_bytes
        )

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> Server:
        """Bind the socket (OSError if the address is unusable) and start the I/O thread."""
        if self._thread is not None:
            raise RuntimeError("server already started")
        opts = self.options
        check_exposure(opts.bind, opts.keys_dir, opts.insecure)  # InsecureBindError
        curve = CurveServer(opts.keys_dir) if opts.keys_dir is not None else None
        self._ctx = zmq.Context()
        if curve is not None:  # ZAP handler first: it must see the first handshake
            curve.start(self._ctx)
            self._curve = curve
        seed_routing_ids()  # the ROUTER's first automatic routing id: not guessable
        router = self._ctx.socket(zmq.ROUTER)
        if curve is not None:
            curve.apply(router)
        router.setsockopt(zmq.ROUTER_MANDATORY, 1)  # unknown peer / full queue: an error, not
        router.setsockopt(zmq.SNDHWM, opts.send_hwm)  # a silent drop (we count the drops)
        router.setsockopt(zmq.RCVHWM, opts.receive_hwm)
        router.setsockopt(zmq.MAXMSGSIZE, opts.max_message_bytes)
        router.setsockopt(zmq.LINGER, 0)
        try:
            router.bind(opts.bind)
        except zmq.ZMQError as exc:
            router.close()
            self._stop_curve()
            self._ctx.term()
            raise OSError(
                f"cannot bind {opts.bind!r}: {exc}; give --bind tcp://127.0.0.1:PORT "
                "(or another address, with --keys) with a free port"
            ) from None
        self._router = router
        self.endpoint = router.getsockopt_string(zmq.LAST_ENDPOINT)
        self.port = int(self.endpoint.rsplit(":", 1)[1])
        # a remote step (RayCompute) only waits in its threads: one per session, so that
        # sessions on different actors never queue behind each other here
        threads = max(opts.workers, opts.max_sessions) if self._remote else opts.workers
        self._executor = ThreadPoolExecutor(threads, thread_name_prefix="arlight-worker")
        self.scheduler = Scheduler(threads, reserve_light=not self._remote)
        self._thread = threading.Thread(target=self._run, name="arlight-server-io", daemon=True)
        self._thread.start()
        log.info(
            "arlight server listening on %s (%d workers, credits %d, heartbeat %.1f s, "
            "session timeout %.0f s; %s)",
            self.endpoint,
            opts.workers,
            opts.credits,
            opts.heartbeat_interval_s,
            opts.session_timeout_s,
            "CURVE: authorised client keys only" if curve else "no encryption",
        )
        log.info(
            "budgets: %.0f s per frame (--frame-deadline), %.0f MiB per session "
            "(--session-memory-mb); sessions' memory at most %d x %.0f MiB = %.1f GiB "
            "(--max-sessions)",
            opts.frame_deadline_s,
            opts.session_memory_bytes / 2**20,
            opts.max_sessions,
            opts.session_memory_bytes / 2**20,
            opts.max_sessions * opts.session_memory_bytes / 2**30,
        )
        return self

    def _stop_curve(self) -> None:
        if self._curve is not None:  # before the context ends: its ZAP socket lives there
            self._curve.stop()
            self._curve = None

    @property
    def connect_address(self) -> str:
        """An address a client on this machine can connect to (tcp://127.0.0.1:PORT)."""
        if self.endpoint is None:
            raise RuntimeError("server not started")
        host = self.endpoint.rsplit(":", 1)[0].replace("tcp://", "")
        if host in ("0.0.0.0", "*", "[::]", "::"):
            host = "127.0.0.1"
        return f"tcp://{host}:{self.port}"

    def stop(self, timeout: float | None = None) -> None:
        """Shut down cleanly (see the module docstring) and wait for it; idempotent."""
        self._stop_requested.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the server has stopped; True if it has."""
        return self._stopped.wait(timeout)

    def wait_workers(self, timeout: float) -> bool:
        """After stop(): wait up to `timeout` seconds for the worker threads' jobs to end;
        True if none is left (a job abandoned at shutdown ends at its next stage boundary;
        one stuck inside a stage does not, and `arlight serve` then exits without it)."""
        with self._busy_lock:
            return self._busy_lock.wait_for(lambda: self._busy == 0, timeout)

    def __enter__(self) -> Server:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc) -> None:
        self.stop()

    def snapshot(self) -> dict:
        """Counters per session and the peers (for tests and logs; read from any thread)."""
        sessions = {name: s.snapshot() for name, s in list(self.sessions.items())}
        return {
            "sessions": sessions,
            "peers": len(self.peers),
            "displays": {k: len(v) for k, v in list(self.displays.items())},
            "errors_sent": self.stats.errors_sent,
            "display_results_dropped": self.stats.display_results_dropped,
            "sessions_expired": self.stats.sessions_expired,
            "peers_expired": self.stats.peers_expired,
        }

    # ------------------------------------------------------------------ I/O thread

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already awake (buffer full) or closed

    def _run(self) -> None:
        opts = self.options
        router = self._router
        poller = zmq.Poller()
        poller.register(router, zmq.POLLIN)
        poller.register(self._wake_r.fileno(), zmq.POLLIN)
        now = time.monotonic()
        next_heartbeat = now + opts.heartbeat_interval_s
        next_housekeeping = now + min(opts.heartbeat_interval_s, 1.0)
        next_log = now + opts.log_interval_s
        try:
            while True:
                now = time.monotonic()
                wait_s = max(0.0, min(next_heartbeat, next_housekeeping, next_log) - now)
                events = dict(poller.poll(int(wait_s * 1000) + 1))
                read_all = not events.get(router) or self._drain_router()
                if events.get(self._wake_r.fileno()):
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except (BlockingIOError, OSError):
                        pass
                self._drain_completions()
                now = time.monotonic()
                if now >= next_heartbeat:
                    self._send_heartbeats()
                    next_heartbeat = now + opts.heartbeat_interval_s
                if now >= next_housekeeping:
                    if read_all:  # a peer's messages still unread are no silence
                        expire_peers(self, now)
                    expire_sessions(self, now)
                    self.hellos.forget_idle(now)
                    self._error_log.flush(now)
                    next_housekeeping = now + min(opts.heartbeat_interval_s, 1.0)
                if now >= next_log:
                    log_rates(self, now, opts.log_interval_s)
                    next_log = now + opts.log_interval_s
                if self._stop_requested.is_set() and not self._draining:
                    begin_drain(self, now)
                if self._draining and (drained(self) or now >= self._drain_deadline):
                    finish_shutdown(self)
                    return
        except Exception:  # noqa: BLE001 - a bug in the loop: log it, still close cleanly
            log.exception("server I/O loop failed; shutting down")
            finish_shutdown(self)
        finally:
            self._stopped.set()

    @property
    def _socket(self) -> zmq.Socket:
        """The ROUTER socket (the I/O thread's; there is one once started)."""
        if self._router is None:
            raise RuntimeError("server not started")
        return self._router

    def _drain_router(self) -> bool:
        """Read and handle what the socket holds, within MAX_MESSAGES_PER_POLL and
        MAX_READ_S_PER_POLL; True when it is empty (every message so far read)."""
        router = self._socket
        until = time.monotonic() + MAX_READ_S_PER_POLL
        for _ in range(MAX_MESSAGES_PER_POLL):
            if time.monotonic() > until:
                return False  # the completions go out, then the socket is read again
            try:
                message = router.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return True
            now = time.monotonic()
            receive_time_wall = time.time()
            identity = message[0].bytes
            parts = [frame.buffer for frame in message[1:]]
            self.stats.messages += 1
            client = client_of(message[-1], identity)  # its key or address (server/clients.py)
            try:
                handle_message(self, identity, parts, now, receive_time_wall, client)
            except Exception as exc:  # noqa: BLE001 - bad input never crashes the server
                log.exception("unexpected failure handling a message from %s", identity.hex())
                self._send_error(
                    identity,
                    Error(
                        code="internal", message=f"the server failed to handle this message ({exc})"
                    ),
                )
        return False

    # ------------------------------------------------------------------ work

    def _schedule(self, session: Session) -> None:
        """`session` may have a frame for a worker: queue its turn, start what may start."""
        frames = session.queue
        if frames.in_flight is None and frames.pending:
            cost = session.setup.cost
            self.scheduler.add(session, cost.frame_s if cost is not None else 0.0)
            self.scheduler.wait(session)
        self._dispatch()

    def _dispatch(self) -> None:
        """Give each free worker the frame of the session whose turn it is
        (server/scheduler.py: fair shares, one worker kept for light sessions)."""
        now = time.monotonic()
        while (key := self.scheduler.next(now)) is not None:
            session = cast(Session, key)  # the scheduler's keys are the sessions
            job = session.queue.next_job()
            if job is None:  # its frames went meanwhile (a shutdown dropped them)
                self.scheduler.finished(session, 0.0, now)
                continue
            self._submit(session, job)

    def _submit(self, session: Session, job: Job) -> None:
        """Hand `job`, now in its session's worker slot, to the worker pool."""
        if self._executor is None:
            raise RuntimeError("server not started")
        self._executor.submit(self._work, session, job)

    def _work(self, session: Session, job: Job) -> None:
        """Worker thread: process one frame (`run_frame`, server/worker.py), turn its
        outcome into its reply (`reply_to`, server/results.py) and hand that to the I/O
        thread. Every job hands one back, whatever fails: the session's slot is always
        freed."""
        with self._busy_lock:
            self._busy += 1
        start = time.monotonic()
        outcome = None
        try:
            if self.options.workers > 1 and not self._remote and not concurrent_pipelines_safe():
                with self._compute_lock:
                    step = run_frame(job, session.compute)
            else:
                step = run_frame(job, session.compute)
            outcome = reply_to(session, job, step)
        except BaseException as exc:  # noqa: BLE001 - reported to the client as internal
            log.error("session %s: frame %d: worker failed: %r", session.name, job.seq, exc)
            outcome = error_reply(
                session,
                job,
                Error(
                    code="internal",
                    seq=job.seq,
                    message=f"the server failed to process this frame ({type(exc).__name__})",
                ),
            )
        finally:
            if outcome is None:  # error_reply itself failed: the bare minimum, still answered
                error = Error("internal", "the server failed to process this frame", None, job.seq)
                outcome = Reply(session, job, encode(error), time.monotonic(), error)
            outcome.worker_s = time.monotonic() - start
            self._completions.put(outcome)
            self._wake()
            with self._busy_lock:
                self._busy -= 1
                self._busy_lock.notify_all()

    def _drain_completions(self) -> None:
        while True:
            try:
                outcome = self._completions.get_nowait()
            except queue.Empty:
                return
            try:
                self._complete(outcome)
            except Exception:  # noqa: BLE001 - a bug: the other outcomes still go out
                log.exception(
                    "session %s: failed to deliver the outcome of frame %d",
                    outcome.session.name,
                    outcome.job.seq,
                )

    def _complete(self, outcome: Reply) -> None:
        """Free the session's slot, send the outcome, start the session's next frame."""
        session, job, error = outcome.session, outcome.job, outcome.error
        frames = session.queue
        current = self.sessions.get(session.name) is session  # not closed or replaced
        lost: list[Job] = []
        if current and error is not None and error.field == ErrorField.PIPELINE_LOST:
            lost = frames.unaccept(job)  # the queued frames go back to the client too
        if current and self._draining and not session.lossless:
            frames.drop_pending()
        final = error is None or not error.retryable  # kept for a resent duplicate
        frames.finish(
            job,
            outcome.parts,
            final=final,
            processed=error is None,
            finish_time_mono=outcome.finish_time_mono,
            start_next=False,  # the scheduler gives the next turn
        )
        self.scheduler.finished(session, outcome.worker_s, time.monotonic())
        if session.capture_peer is not None:
            self._send(session.capture_peer, outcome.parts)
        if error is None:
            for identity in watchers(self, session):
                if not self._send(identity, outcome.parts):
                    session.display_drops += 1
                    self.stats.display_results_dropped += 1
        else:
            self.stats.errors_sent += 1
            self.stats.error_codes[error.code] += 1
        if not current:
            self._dispatch()
            return
        if error is not None and error.field == ErrorField.PIPELINE_LOST:
            self._pipeline_lost(session, job, lost)
        self._schedule(session)  # its next frame's turn, and any other session's
        if session.ended and session.idle:
            close_session(self, session, "end of stream")

    def _pipeline_lost(self, session: Session, job: Job, queued: list[Job]) -> None:
        """The session's pipeline (a Ray actor) was lost with `job`: its `queued` frames,
        un-accepted, are reported retryable too; the client sends them all again, in seq
        order, to the session's next pipeline."""
        log.warning(
            "session %s: pipeline lost at frame %d; it and %d queued frame(s) reported "
            "retryable (pipeline_lost), to be sent again to a new pipeline",
            session.name,
            job.seq,
            len(queued),
        )
        for other in queued:
            error = Error(
                code="bad_state",
                field=ErrorField.PIPELINE_LOST,
                seq=other.seq,
                retryable=True,
                message="the session's pipeline was lost before this "
                "frame was processed: send it again",
            )
            if session.capture_peer is not None:
                self._send_error(session.capture_peer, error)

    # ------------------------------------------------------------------ sending

    def _send(self, identity: bytes, parts: list) -> bool:
        """Send without blocking; False if the peer is gone or its queue is full (dropped)."""
        try:
            self._socket.send_multipart([identity, *parts], zmq.NOBLOCK, copy=False)
            return True
        except zmq.Again:
            peer = self.peers.get(identity)
            if peer is not None:
                peer.results_dropped += 1
            return False
        except zmq.ZMQError as exc:
            if exc.errno == zmq.EHOSTUNREACH:  # disconnected: forget it
                peer = self.peers.get(identity)
                if peer is not None:
                    detach_peer(self, peer, reason="disconnected")
                return False
            raise

    def _send_error(self, identity: bytes, error: Error) -> None:
        self.stats.errors_sent += 1
        self.stats.error_codes[error.code] += 1
        self._error_log.sent(identity, error, time.monotonic())
        self._send(identity, encode_error(error))

    def _send_heartbeats(self) -> None:
        parts = encode(Heartbeat(time.time()))
        for identity in list(self.peers):
            self._send(identity, parts)
