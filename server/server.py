"""The streaming server: one ZeroMQ ROUTER socket, one I/O thread, a pool of worker threads.

Transport (protocols/SPEC.md): every client, capture or display, talks to the one ROUTER
through a DEALER; the ROUTER prepends the peer's identity frame. Only the I/O thread touches
the socket. It routes frames to their session's queue (server/frame_queue.py), hands at most
one frame per session to the worker pool (so a session's frames stay in order), where
`run_frame` (server/worker.py) processes it, and sends the replies back to the capture peer
and to every display peer subscribed to the session. A worker turns the frame's outcome into
its encoded Result (server/results.py), reports through a queue and wakes the I/O thread
through a socket pair it polls.

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
from dataclasses import dataclass, field

import zmq

from arlight.pipeline.runtime import concurrent_pipelines_safe
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    Credit,
    Error,
    ErrorField,
    Heartbeat,
    Hello,
    ProtocolError,
    SessionConfig,
    Welcome,
    decode,
    encode,
    error_from_exception,
    new_token,
    peek_header,
)
from arlight.protocols.fields import MAX_INT as MAX_SEQ  # a Frame's seq: 0..2^63-1
from arlight.server.budget import SessionBudget
from arlight.server.frame_queue import Job, Offer
from arlight.server.options import DEFAULT_BIND, ServerOptions  # noqa: F401 - DEFAULT_BIND too
from arlight.server.results import ErrorLog, Reply, encode_error, error_reply, reply_to
from arlight.server.security import (
    CurveServer,
    check_exposure,
    tokens_equal,
    unauthorized_error,
)
from arlight.server.session import Session, SessionSetupError
from arlight.server.worker import ProcessStep, run_frame

log = logging.getLogger(__name__)

MAX_MESSAGES_PER_POLL = 256  # fairness between reading the socket and sending results


@dataclass
class Peer:
    """A connected client. role: "capture" or "display"; session: the session name."""

    identity: bytes
    role: str
    session: str
    client_name: str
    last_seen: float  # time.monotonic() of its last message, seconds
    results_dropped: int = 0  # Results not delivered because its queue was full
    token: str | None = None  # a display's token, checked again when its session is created

    @property
    def label(self) -> str:
        name = f" {self.client_name!r}" if self.client_name else ""
        return f"{self.role} peer {self.identity.hex()}{name}"


@dataclass
class ServerStats:
    messages: int = 0
    errors_sent: int = 0
    peers_expired: int = 0
    sessions_expired: int = 0
    sessions_closed: int = 0
    display_results_dropped: int = 0  # Results not delivered to a display (its queue full)
    error_codes: collections.Counter = field(default_factory=collections.Counter)


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
                if events.get(router):
                    self._drain_router()
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
                    self._expire_peers(now)
                    self._expire_sessions(now)
                    self._error_log.flush(now)
                    next_housekeeping = now + min(opts.heartbeat_interval_s, 1.0)
                if now >= next_log:
                    self._log_rates(now, opts.log_interval_s)
                    next_log = now + opts.log_interval_s
                if self._stop_requested.is_set() and not self._draining:
                    self._begin_drain(now)
                if self._draining and (self._drained() or now >= self._drain_deadline):
                    self._finish_shutdown()
                    return
        except Exception:  # noqa: BLE001 - a bug in the loop: log it, still close cleanly
            log.exception("server I/O loop failed; shutting down")
            self._finish_shutdown()
        finally:
            self._stopped.set()

    @property
    def _socket(self) -> zmq.Socket:
        """The ROUTER socket (the I/O thread's; there is one once started)."""
        if self._router is None:
            raise RuntimeError("server not started")
        return self._router

    def _drain_router(self) -> None:
        router = self._socket
        for _ in range(MAX_MESSAGES_PER_POLL):
            try:
                message = router.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return
            now = time.monotonic()
            receive_time_wall = time.time()
            identity = message[0].bytes
            parts = [frame.buffer for frame in message[1:]]
            self.stats.messages += 1
            try:
                self._handle(identity, parts, now, receive_time_wall)
            except Exception as exc:  # noqa: BLE001 - bad input never crashes the server
                log.exception("unexpected failure handling a message from %s", identity.hex())
                self._send_error(
                    identity,
                    Error(
                        code="internal", message=f"the server failed to handle this message ({exc})"
                    ),
                )

    def _handle(self, identity: bytes, parts: list, now: float, receive_time_wall: float) -> None:
        """One message from a peer; now: time.monotonic(), receive_time_wall: time.time()."""
        peer = self.peers.get(identity)
        if peer is not None:
            peer.last_seen = now
        if not parts:
            self._send_error(identity, Error(code="malformed", message="empty message"))
            return
        try:
            header = peek_header(parts)
        except ProtocolError as exc:
            self._send_error(identity, error_from_exception(exc))
            return
        if header["type"] == "frame":  # routed undecoded: a worker decodes it, and a
            # live frame replaced in the queue costs no decoding at all
            self._on_frame(identity, peer, header, parts, now, receive_time_wall)
            return
        try:
            message = decode(
                parts,
                max_message_bytes=self.options.max_message_bytes,
                max_pixels=self.options.max_pixels,
            )
        except ProtocolError as exc:
            self._send_error(identity, error_from_exception(exc))
            return
        if isinstance(message, Hello):
            self._on_hello(identity, message, now)
        elif isinstance(message, Heartbeat):
            if peer is None:  # e.g. after a server restart: tell the client to say Hello again
                self._send_error(
                    identity,
                    Error(
                        code="bad_state",
                        field=ErrorField.SESSION,
                        retryable=True,
                        message="unknown peer: send Hello first (the server may have restarted)",
                    ),
                )
        elif isinstance(message, Bye):
            self._on_bye(identity, peer, message)
        elif isinstance(message, (Credit, Error)):
            if isinstance(message, Error):
                log.info(
                    "client %s reported an error: %s %s",
                    identity.hex(),
                    message.code,
                    message.message,
                )
        else:
            self._send_error(
                identity,
                Error(
                    code="bad_state",
                    field=ErrorField.TYPE,
                    message=f"a client may send Hello, Frame, Heartbeat, Credit or Bye, "
                    f"not {type(message).__name__}",
                ),
            )

    def _on_hello(self, identity: bytes, hello: Hello, now: float) -> None:
        cfg = hello.config
        name = cfg.session  # 1..64 characters of [A-Za-z0-9_.-]: decode() checked it
        old = self.peers.get(identity)
        if old is not None:
            self._detach_peer(old, reason="said Hello again")
        if cfg.role == "display":
            if not self._display_admitted(identity, cfg):
                return  # refused: the Error is sent
            self.peers[identity] = Peer(
                identity, "display", name, cfg.client_name, now, token=cfg.token
            )
            self.displays[name].add(identity)
            log.info("session %s: display peer %s subscribed", name, identity.hex())
            self._send_welcome(identity, name, credits=0)
            return
        if self._draining:
            self._send_error(
                identity,
                Error(
                    code="bad_state",
                    field=ErrorField.SHUTDOWN,
                    retryable=True,
                    message="the server is shutting down",
                ),
            )
            return
        session = self._capture_session(identity, cfg)
        if session is None:
            return  # refused: the Error is sent
        session.capture_peer = identity
        session.ended = False
        session.last_activity = now
        self.peers[identity] = Peer(identity, "capture", name, cfg.client_name, now)
        # the token goes only to a client that sent one (older clients refuse the key)
        self._send_welcome(
            identity,
            name,
            credits=self.options.credits,
            token=session.token if cfg.token is not None else None,
        )

    def _send_welcome(
        self, identity: bytes, session: str, credits: int, token: str | None = None
    ) -> None:
        self._send(
            identity,
            encode(
                Welcome(
                    PROTOCOL_VERSION,
                    session,
                    credits,
                    self.options.heartbeat_interval_s,
                    self.options.name,
                    token,
                )
            ),
        )

    # ------------------------------------------------------------------ session tokens

    def _may_enter(self, token: str | None, session: Session | None) -> bool:
        """The token admits to `session` (None: any, checked again when it is created)."""
        if not self.options.session_tokens or tokens_equal(token, self.admin_token):
            return True
        return tokens_equal(token, session.token) if session is not None else token is not None

    def _refuse_unauthorized(self, identity: bytes, name: str, role: str) -> None:
        self._send_error(identity, unauthorized_error(name, role))

    def _display_admitted(self, identity: bytes, cfg: SessionConfig) -> bool:
        """A display Hello's token: the session's, the admin token, or, for a session that
        does not exist yet, any token (checked when the session is created)."""
        if self._may_enter(cfg.token, self.sessions.get(cfg.session)):
            return True
        self._refuse_unauthorized(identity, cfg.session, "display")
        return False

    def _check_subscribers(self, session: Session) -> None:
        """A new session: unsubscribe (with an Error) every display whose token does not
        admit it, before any of its Results is sent."""
        for identity in list(self.displays.get(session.name, ())):
            peer = self.peers.get(identity)
            if peer is not None and not self._may_enter(peer.token, session):
                self._refuse_unauthorized(identity, session.name, "display")
                self._detach_peer(peer, reason="wrong token")

    def _capture_session(self, identity: bytes, cfg: SessionConfig) -> Session | None:
        """The session a capture Hello resumes or creates (section 3 of SPEC.md, "Handshake");
        None after sending the Error that refuses it."""
        name = cfg.session
        session = self.sessions.get(name)
        if session is not None and not self._may_enter(cfg.token, session):
            self._refuse_unauthorized(identity, name, "capture")
            return None
        if session is not None and not session.same_setup(cfg):
            owner = self.peers.get(session.capture_peer) if session.capture_peer else None
            if owner is not None:
                self._send_error(
                    identity,
                    Error(
                        code="bad_state",
                        field="hello.config.session",
                        message=f"session {name!r} is in use by another capture client with a "
                        "different configuration; choose another session name (--session)",
                    ),
                )
                return None
            self._close_session(session, "replaced by a new configuration")
            session = None
        if session is not None:
            previous = session.capture_peer
            if previous is not None and previous != identity and previous in self.peers:
                self._detach_peer(self.peers[previous], reason="replaced by a reconnect")
            log.info(
                "session %s: capture peer %s resumed it (last seq %d)",
                name,
                identity.hex(),
                session.queue.highest_seq,
            )
            return session
        if len(self.sessions) >= self.options.max_sessions:
            self._send_error(
                identity,
                Error(
                    code="too_large",
                    field="hello.config.session",
                    message=f"the server already holds {len(self.sessions)} sessions "
                    f"(limit {self.options.max_sessions}, `arlight serve --max-sessions`); "
                    "try again later",
                ),
            )
            return None
        try:
            session = Session(
                cfg,
                credits=self.options.credits,
                max_pixels=self.options.max_pixels,
                max_message_bytes=self.options.max_message_bytes,
                process=self._process,
                budget=self.budget,
                cancel=self._cancel,
            )
        except SessionSetupError as exc:
            self._send_error(
                identity, Error(code=exc.code, field=f"hello.config.{exc.field}", message=str(exc))
            )
            return None
        # the client's own token, or one the server makes (never the admin token: the Welcome
        # tells it, and whoever learns a session's token should learn no more than that)
        session.token = (
            cfg.token
            if cfg.token and not tokens_equal(cfg.token, self.admin_token)
            else new_token()
        )
        self.sessions[name] = session
        self._check_subscribers(session)
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

    def _on_frame(
        self,
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
            self._send_error(
                identity,
                Error(
                    code="bad_field",
                    field="frame.seq",
                    message=f"seq must be an integer in 0..2^63-1, got {shown}",
                ),
            )
            return
        session = self.sessions.get(peer.session) if peer is not None else None
        if (
            peer is None
            or peer.role != "capture"
            or session is None
            or session.capture_peer != identity
        ):
            self._send_error(
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
        if self._draining:
            self._send_error(
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
            self._send(identity, frames.reply(seq))
        elif offer is Offer.EXPIRED:  # answer it, or a lossless client would wait forever
            self._send_error(
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
            self._send_error(
                identity,
                Error(
                    code="bad_state",
                    field=ErrorField.CREDITS,
                    seq=seq,
                    retryable=True,
                    message=f"more than {self.options.credits} frames unacknowledged in lossless "
                    "mode; wait for Results (credits) before sending more",
                ),
            )
        self._schedule(session)

    def _on_bye(self, identity: bytes, peer: Peer | None, bye: Bye) -> None:
        if peer is None:
            return
        log.info("session %s: %s said Bye (%s)", peer.session, peer.label, bye.reason or "")
        session = self.sessions.get(peer.session)
        self._detach_peer(peer, reason="said Bye")
        if peer.role == "capture" and session is not None and session.capture_peer is None:
            session.ended = True
            if session.idle:
                self._close_session(session, "end of stream")

    # ------------------------------------------------------------------ work

    def _schedule(self, session: Session) -> None:
        job = session.queue.next_job()
        if job is not None:
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
        next_job = frames.finish(
            job,
            outcome.parts,
            final=final,
            processed=error is None,
            finish_time_mono=outcome.finish_time_mono,
            start_next=current,
        )
        if session.capture_peer is not None:
            self._send(session.capture_peer, outcome.parts)
        if error is None:
            for identity in list(self.displays.get(session.name, ())):
                if not self._send(identity, outcome.parts):
                    session.display_drops += 1
                    self.stats.display_results_dropped += 1
        else:
            self.stats.errors_sent += 1
            self.stats.error_codes[error.code] += 1
        if not current:
            return
        if error is not None and error.field == ErrorField.PIPELINE_LOST:
            self._pipeline_lost(session, job, lost)
        if next_job is not None:
            self._submit(session, next_job)
        if session.ended and session.idle:
            self._close_session(session, "end of stream")

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
                    self._detach_peer(peer, reason="disconnected")
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

    # ------------------------------------------------------------------ housekeeping

    def _detach_peer(self, peer: Peer, reason: str) -> None:
        self.peers.pop(peer.identity, None)
        if peer.role == "display":
            subscribers = self.displays.get(peer.session)
            if subscribers is not None:
                subscribers.discard(peer.identity)
                if not subscribers:
                    del self.displays[peer.session]
        else:
            session = self.sessions.get(peer.session)
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

    def _close_session(self, session: Session, reason: str) -> None:
        """Forget a session (its Pipeline is freed); displays get Bye at the end of a stream."""
        if self.sessions.get(session.name) is session:
            del self.sessions[session.name]
        self.stats.sessions_closed += 1
        release = getattr(self._process, "release", None)  # `serve --ray`: the session's actor
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
        if session.capture_peer is not None and session.capture_peer in self.peers:
            self._detach_peer(self.peers[session.capture_peer], reason=reason)
        if reason == "end of stream":
            parts = encode(Bye(f"session {session.name} ended", ByeKind.END_OF_STREAM))
            for identity in list(self.displays.get(session.name, ())):
                self._send(identity, parts)

    def _expire_peers(self, now: float) -> None:
        limit = self.options.liveness * self.options.heartbeat_interval_s
        for peer in list(self.peers.values()):
            if now - peer.last_seen > limit:
                self.stats.peers_expired += 1
                log.warning(
                    "session %s: %s silent for %.1f s: declared dead",
                    peer.session,
                    peer.label,
                    now - peer.last_seen,
                )
                self._detach_peer(peer, reason="dead")

    def _expire_sessions(self, now: float) -> None:
        for session in list(self.sessions.values()):
            if session.idle and now - session.last_activity > self.options.session_timeout_s:
                self.stats.sessions_expired += 1
                self._close_session(session, f"idle for {now - session.last_activity:.0f} s")

    def _log_rates(self, now: float, interval_s: float) -> None:
        for session in list(self.sessions.values()):
            line = session.rate_line(now, interval_s, len(self.displays.get(session.name, ())))
            if line is not None:
                log.info("%s", line)

    # ------------------------------------------------------------------ shutdown

    def _begin_drain(self, now: float) -> None:
        self._draining = True
        self._drain_deadline = now + self.options.shutdown_grace_s
        waiting = 0
        for session in self.sessions.values():
            frames = session.queue
            if frames.lossless:
                waiting += len(frames.pending) + (frames.in_flight is not None)
            else:
                frames.drop_pending()
        log.info(
            "shutting down: %d lossless frame(s) still to finish (grace %g s)",
            waiting,
            self.options.shutdown_grace_s,
        )

    def _drained(self) -> bool:
        return all(
            s.queue.in_flight is None and not (s.lossless and s.queue.pending)
            for s in self.sessions.values()
        )

    def _finish_shutdown(self) -> None:
        """Report unfinished lossless frames, say Bye to every peer, close the socket."""
        router = self._socket
        self._cancel.set()  # a frame still in a worker is abandoned at its next stage
        try:
            for session in list(self.sessions.values()):
                in_flight = session.queue.in_flight
                unfinished = [in_flight] if in_flight else []
                unfinished += session.queue.drop_pending()
                if session.capture_peer is not None:
                    for job in unfinished:
                        self._send_error(
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
                        "session %s: %d frame(s) not processed at shutdown (reported "
                        "to the client)",
                        session.name,
                        len(unfinished),
                    )
            bye = encode(Bye("server shutting down", ByeKind.SHUTDOWN))
            for identity in list(self.peers):
                self._send(identity, bye)
            router.setsockopt(zmq.LINGER, 1000)  # let the Byes and last Results out
        except Exception:  # noqa: BLE001
            log.exception("error while shutting down")
        finally:
            router.close()
            if self._executor is not None:
                self._executor.shutdown(wait=False, cancel_futures=True)
            self._stop_curve()
            if self._ctx is not None:
                self._ctx.term()
            self._wake_r.close()
            self._wake_w.close()
            self.sessions.clear()
            log.info("server stopped")
