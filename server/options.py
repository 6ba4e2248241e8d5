"""Every limit and interval of the streaming server, with its default (`ServerOptions`), and
the `arlight serve` flag that sets each (`SERVE_FLAGS`, for error messages)."""

from __future__ import annotations

from dataclasses import dataclass

from arlight.protocols import DEFAULT_MAX_MESSAGE_BYTES, DEFAULT_MAX_PIXELS, TOKEN_RE

DEFAULT_PORT = 5555
DEFAULT_BIND = f"tcp://127.0.0.1:{DEFAULT_PORT}"  # this machine only (docs/guides/security.md)


# the `arlight serve` flag of each ServerOptions field that has one (for error messages)
SERVE_FLAGS = {
    "bind": "--bind",
    "workers": "--workers",
    "credits": "--credits",
    "heartbeat_interval_s": "--heartbeat",
    "session_timeout_s": "--session-timeout",
    "log_interval_s": "--log-interval",
    "max_sessions": "--max-sessions",
    "max_sessions_per_client": "--max-sessions-per-client",
    "hellos_per_client_s": "--hellos-per-client",
    "max_message_bytes": "--max-message-mb",
    "shutdown_grace_s": "--shutdown-grace",
    "keys_dir": "--keys",
    "admin_token": "--admin-token-file",
    "frame_deadline_s": "--frame-deadline",
    "session_memory_bytes": "--session-memory-mb",
}


@dataclass(frozen=True)
class ServerOptions:
    """Every server limit and interval (seconds), with its default."""

    bind: str = DEFAULT_BIND
    workers: int = 2  # worker threads running Pipeline.process (one frame per session at a time)
    credits: int = 4  # lossless credit window: frames a capture client may have unacknowledged
    heartbeat_interval_s: float = 1.0
    liveness: int = 3  # missed heartbeat intervals before a peer is declared dead
    session_timeout_s: float = 60.0  # a session with no frames for this long expires
    log_interval_s: float = 5.0  # per-session frame rate and latency log lines
    max_sessions: int = 32
    # per client (a CURVE key, or a network address: server/clients.py): sessions its Hellos
    # created and still open, and Hellos a second (after a burst of 20)
    max_sessions_per_client: int = 8
    hellos_per_client_s: float = 5.0
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_pixels: int = DEFAULT_MAX_PIXELS
    send_hwm: int = 32  # messages queued per peer before sends to it are dropped
    receive_hwm: int = 256
    shutdown_grace_s: float = 10.0  # time given to lossless frames received before stop()
    name: str = "arlight"
    # security (server/security.py): CURVE keys folder (server.key_secret, authorized/*.key);
    # insecure: allow a non-loopback bind without keys (warned); admin_token: admits a display
    # to any session (None: one is generated, Server.admin_token); session_tokens False: no
    # token is checked (in-process tests of other features only)
    keys_dir: str | None = None
    insecure: bool = False
    admin_token: str | None = None
    session_tokens: bool = True
    # budgets (server/budget.py): a frame in the pipeline longer than this is abandoned
    # between stages (Error "deadline"); a Hello whose frames could not meet it is refused
    frame_deadline_s: float = 60.0
    session_memory_bytes: int = 1024 * 2**20  # per session; the server's: max_sessions x this

    def __post_init__(self) -> None:
        checks = {
            "workers": self.workers >= 1,
            "credits": self.credits >= 1,
            "heartbeat_interval_s": self.heartbeat_interval_s > 0,
            "liveness": self.liveness >= 1,
            "session_timeout_s": self.session_timeout_s > 0,
            "log_interval_s": self.log_interval_s > 0,
            "max_sessions": self.max_sessions >= 1,
            "max_sessions_per_client": self.max_sessions_per_client >= 1,
            "hellos_per_client_s": self.hellos_per_client_s > 0,
            "send_hwm": self.send_hwm >= 1,
            "receive_hwm": self.receive_hwm >= 1,
            "max_message_bytes": self.max_message_bytes >= 1024,
            "max_pixels": self.max_pixels >= 1,
            "shutdown_grace_s": self.shutdown_grace_s >= 0,
            "frame_deadline_s": self.frame_deadline_s > 0,
            "session_memory_bytes": self.session_memory_bytes >= 2**20,
        }
        for name, ok in checks.items():
            if not ok:
                flag = SERVE_FLAGS.get(name)
                raise ValueError(
                    f"server option {name}{f' ({flag})' if flag else ''} is out of "
                    f"range: {getattr(self, name)!r}"
                )
        if self.admin_token is not None and not TOKEN_RE.fullmatch(self.admin_token):
            raise ValueError(
                "server option admin_token (--admin-token-file) must be 16..128 "
                "characters from A-Z a-z 0-9 _ -"
            )  # the value is a secret: unsaid
