"""The server's records of its peers and its counters (server/server.py keeps them)."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field


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
