"""`arlight serve`: the streaming server (sessions, live/lossless delivery, budgets)."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from arlight.cli.common import (
    RAY_ADDRESS,
    BadInput,
    at_least_1_mb,
    check_address,
    positive_float,
    positive_int,
)
from arlight.protocols import DEFAULT_MAX_MESSAGE_BYTES
from arlight.server.security import read_token_file
from arlight.server.server import DEFAULT_BIND, Server, ServerOptions
from arlight.server.watchdog import start_exit_watchdog

WORKER_EXIT_WAIT_S = 2.0  # after the grace, for a worker to reach its next stage boundary


def add_parser(sub) -> None:
    defaults = ServerOptions()
    serve = sub.add_parser(
        "serve",
        help="run the streaming server (sessions, live/lossless delivery)",
        description="Run the arlight streaming server: capture clients stream RGB-D frames "
        "into named sessions (each with its own pipeline state); Results go back "
        "to the capture client and to every display client subscribed to the "
        "session. Logs each session's frame rate and latency. SIGINT/SIGTERM shut "
        "it down cleanly.",
    )
    serve.add_argument(
        "--bind",
        default=DEFAULT_BIND,
        metavar="ADDRESS",
        help=f"ZeroMQ address to listen on (default {DEFAULT_BIND}: this "
        "machine only); any other address needs --keys (or --insecure)",
    )
    serve.add_argument(
        "--keys",
        metavar="DIR",
        help="CURVE keys from `arlight keys generate DIR`: encrypt the traffic "
        "and admit only clients whose public keys are in DIR/authorized/",
    )
    serve.add_argument(
        "--insecure",
        action="store_true",
        help="allow a --bind other machines can reach without --keys (no "
        "encryption, any client admitted; warned at every start)",
    )
    serve.add_argument(
        "--admin-token-file",
        metavar="FILE",
        help="a file holding the admin token (a display with it may watch any "
        "session); default: a random one, printed at start",
    )
    serve.add_argument(
        "--workers",
        type=positive_int,
        default=defaults.workers,
        help=f"worker threads running the pipeline (default {defaults.workers}; "
        "one frame per session at a time)",
    )
    serve.add_argument(
        "--credits",
        type=positive_int,
        default=defaults.credits,
        help="lossless credit window: frames a client may have unacknowledged "
        f"(default {defaults.credits})",
    )
    serve.add_argument(
        "--heartbeat",
        type=positive_float,
        default=defaults.heartbeat_interval_s,
        metavar="S",
        help=f"heartbeat interval in seconds; a peer silent for "
        f"{defaults.liveness} intervals is dead "
        f"(default {defaults.heartbeat_interval_s:g})",
    )
    serve.add_argument(
        "--session-timeout",
        type=positive_float,
        default=defaults.session_timeout_s,
        metavar="S",
        help="a session without frames for S seconds expires and frees its "
        f"memory (default {defaults.session_timeout_s:g})",
    )
    serve.add_argument(
        "--log-interval",
        type=positive_float,
        default=defaults.log_interval_s,
        metavar="S",
        help="seconds between per-session rate/latency log lines "
        f"(default {defaults.log_interval_s:g})",
    )
    serve.add_argument(
        "--max-sessions",
        type=positive_int,
        default=defaults.max_sessions,
        help=f"most concurrent sessions (default {defaults.max_sessions})",
    )
    serve.add_argument(
        "--max-sessions-per-client",
        type=positive_int,
        default=defaults.max_sessions_per_client,
        metavar="N",
        help="most sessions one client (a CURVE key, or an address) may hold "
        f"(default {defaults.max_sessions_per_client})",
    )
    serve.add_argument(
        "--hellos-per-client",
        type=positive_float,
        default=defaults.hellos_per_client_s,
        metavar="R",
        help="Hellos a second one client may send after a burst of 20 "
        f"(default {defaults.hellos_per_client_s:g})",
    )
    serve.add_argument(
        "--max-message-mb",
        type=positive_float,
        metavar="MB",
        help="largest message accepted, MiB (default "
        f"{defaults.max_message_bytes / 2**20:g}); a peer sending more is "
        "disconnected",
    )
    serve.add_argument(
        "--shutdown-grace",
        type=float,
        default=defaults.shutdown_grace_s,
        metavar="S",
        help="on SIGINT/SIGTERM, time given to lossless frames "
        "already received (default "
        f"{defaults.shutdown_grace_s:g}); the rest are "
        "reported to their clients",
    )
    _add_budget_options(serve, defaults)
    serve.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run each session's pipeline in a Ray actor (pip install "
        "'arlight[ray]'): --ray or --ray local starts a local Ray, "
        "--ray auto joins this machine's cluster, --ray ray://HOST:10001 "
        "connects to one; the socket and I/O stay in this process. A lost "
        "actor's frames are reported retryable and go to a new actor "
        "(a fresh volume)",
    )
    serve.set_defaults(func=run)


def _add_budget_options(serve, defaults) -> None:
    """`arlight serve`'s budgets (docs/guides/security.md#limits-and-budgets)."""
    serve.add_argument(
        "--frame-deadline",
        type=positive_float,
        default=defaults.frame_deadline_s,
        metavar="S",
        help="a frame still in the pipeline after S seconds is abandoned at "
        "the next stage (Error deadline), and a session whose settings "
        "could not meet it is refused at Hello (default "
        f"{defaults.frame_deadline_s:g})",
    )
    serve.add_argument(
        "--session-memory-mb",
        type=at_least_1_mb,
        default=defaults.session_memory_bytes / 2**20,
        metavar="MB",
        help="memory budget of one session (image buffers, volume): a Hello "
        "over it is refused; the sessions' memory is at most "
        "--max-sessions x this (default "
        f"{defaults.session_memory_bytes / 2**20:g})",
    )


def run(args: argparse.Namespace) -> int:
    check_address(args.bind, "--bind")
    admin_token = None
    if args.admin_token_file:
        admin_token = read_token_file(args.admin_token_file, "--admin-token-file")
    logging.getLogger("arlight.server").setLevel(logging.INFO)
    for handler in logging.getLogger().handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    options = ServerOptions(
        bind=args.bind,
        workers=args.workers,
        credits=args.credits,
        heartbeat_interval_s=args.heartbeat,
        session_timeout_s=args.session_timeout,
        log_interval_s=args.log_interval,
        max_sessions=args.max_sessions,
        max_sessions_per_client=args.max_sessions_per_client,
        hellos_per_client_s=args.hellos_per_client,
        max_message_bytes=int(args.max_message_mb * 2**20)
        if args.max_message_mb
        else DEFAULT_MAX_MESSAGE_BYTES,
        shutdown_grace_s=args.shutdown_grace,
        keys_dir=args.keys,
        insecure=args.insecure,
        admin_token=admin_token,
        frame_deadline_s=args.frame_deadline,
        session_memory_bytes=int(args.session_memory_mb * 2**20),
    )
    compute, started_ray = None, False
    if args.ray is not None:  # each session's pipeline in a Ray actor (arlight/ray_serve.py)
        if not RAY_ADDRESS.fullmatch(args.ray):
            raise BadInput(
                f"--ray expects local, auto or a Ray address such as "
                f"ray://HOST:10001 or HOST:6379, got {args.ray!r}"
            )
        from arlight.ray_serve import RayCompute, connect

        logging.getLogger("arlight.ray_serve").setLevel(logging.INFO)

        ray, started_ray = connect(args.ray)  # BatchUsageError (exit 2): no Ray, no cluster
        compute = RayCompute(ray)
    try:
        return _serve(args, Server(options, process=compute), admin_token)
    finally:
        if compute is not None:
            compute.close()
            if started_ray:
                ray.shutdown()


def _serve(args: argparse.Namespace, server, admin_token: str | None) -> int:
    server.start()  # InsecureBindError, SecurityError: exit 2
    stop = threading.Event()
    signals_seen = []

    def on_signal(signum, _frame) -> None:
        signals_seen.append(signum)
        if len(signals_seen) > 1:
            print("arlight serve: second signal, exiting now", file=sys.stderr, flush=True)
            os._exit(130)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    # a worker holding the interpreter in a stage cannot delay the exit past this
    start_exit_watchdog(args.shutdown_grace + WORKER_EXIT_WAIT_S + 1.0)
    keys = (
        f"; clients need --server-key {Path(args.keys) / 'server.key'} --client-key "
        f"{Path(args.keys) / 'NAME.key_secret'}"
        if args.keys
        else ""
    )
    print(
        f"arlight serve: listening on {server.endpoint} (clients: --server "
        f"{server.connect_address}{keys}); Ctrl-C or SIGTERM stops it",
        file=sys.stderr,
        flush=True,
    )
    if admin_token is None:  # generated: the operator's only way to learn it
        print(
            f"arlight serve: admin token (a display with it may watch any session; keep it "
            f"secret, or give your own with --admin-token-file): {server.admin_token}",
            file=sys.stderr,
            flush=True,
        )
    while not stop.is_set() and not server.wait(0.2):
        pass
    name = signal.Signals(signals_seen[0]).name if signals_seen else "server stopped"
    print(
        f"arlight serve: {name}: shutting down (in-flight lossless frames finish, "
        f"at most {args.shutdown_grace:g} s)",
        file=sys.stderr,
        flush=True,
    )
    server.stop()
    _exit_if_workers_busy(server)
    return 0


def _exit_if_workers_busy(server) -> None:
    """The server has stopped (every unfinished frame reported to its client); a worker
    still inside a pipeline stage would keep the process alive: exit without it."""
    if server.wait_workers(WORKER_EXIT_WAIT_S):
        return
    print(
        "arlight serve: a worker is still inside a pipeline stage; exiting without it "
        "(its frame was reported to the client as not processed)",
        file=sys.stderr,
        flush=True,
    )
    logging.shutdown()
    os._exit(0)
