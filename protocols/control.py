"""The control messages (SPEC.md section 4): Welcome, Credit, Error, Heartbeat and Bye, with
the wire enums ByeKind and ErrorField."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import ClassVar

from .errors import ProtocolError
from .fields import (
    CODE_RE,
    MAX_CREDITS,
    NAME_RE,
    FieldReader,
    WireEnum,
    read_token,
    to_plain,
)
from .images import ImageParts


class ByeKind(WireEnum):
    """Why a Bye was sent (its `kind` on the wire; SPEC.md section 3, "Bye")."""

    END_OF_STREAM = "end_of_stream"  # the stream ended: server -> displays, or a capture
    # client whose source has no more frames
    SHUTDOWN = "shutdown"  # the server is shutting down: reconnect to the restarted server
    LEAVING = "leaving"  # a client leaves before its stream ended (interrupted, closed)


class ErrorField(WireEnum):
    """The `Error.field` values that are not field paths (SPEC.md section 6, "Error fields").

    Compare with `error.field == ErrorField.SESSION` (the members are strings); whether an
    Error may be retried is its own `retryable` flag, not looked up from these.
    """

    HEADER = "header"
    VERSION = "v"
    TYPE = "type"
    SESSION = "session"  # retryable: the server does not know this peer; say Hello again
    SHUTDOWN = "shutdown"  # retryable: the server is shutting down
    CREDITS = "credits"  # retryable: a lossless frame refused for the credit window
    DUPLICATE = "duplicate"  # final: a resent frame whose answer is no longer kept
    # retryable: the session's pipeline (a Ray actor, `arlight serve --ray`) was lost; the
    # frame and the session's queued frames were not processed: send them again now
    PIPELINE_LOST = "pipeline_lost"


@dataclass
class Welcome:
    TYPE: ClassVar[str] = "welcome"
    protocol_version: int
    session: str
    credits: int  # frames the capture client may send before the next Credit (lossless)
    heartbeat_interval_s: float
    server_name: str = "arlight"
    # the session's token (optional key): sent to a capture client whose Hello carried one;
    # displays of the session present it (SPEC.md "session tokens")
    token: str | None = None

    def _pack(self, parts: list) -> dict:
        out = {
            "session": self.session,
            "credits": to_plain(self.credits),
            "heartbeat_interval_s": to_plain(self.heartbeat_interval_s),
            "server_name": self.server_name,
        }
        if self.token is not None:  # optional key: absent when no token is told
            out["token"] = read_token(self.token, "welcome.token")
        return out

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Welcome:
        raw = h.raw("token", nullable=True) if "token" in h.d else None
        token = None if raw is None else read_token(raw, h.f("token"))
        return cls(
            v,
            h.str("session", 64, NAME_RE),
            h.int("credits", 0, MAX_CREDITS),
            h.float("heartbeat_interval_s", 1e-3, 3600.0),
            h.str("server_name", 128),
            token,
        )


@dataclass
class Credit:
    TYPE: ClassVar[str] = "credit"
    credits: int  # lossless flow control: capture may send this many more frames

    def _pack(self, parts: list) -> dict:
        return {"credits": to_plain(self.credits)}

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Credit:
        return cls(h.int("credits", 0, MAX_CREDITS))


@dataclass
class Error:
    """An error report. retryable: the frame `seq` (if any) was not processed and is not
    answered: keep it and send it again (SPEC.md "Retryable Errors"); False: final."""

    TYPE: ClassVar[str] = "error"
    code: str
    message: str
    field: str | None = None  # dotted field path, or an ErrorField (kept as its string)
    seq: int | None = None
    retryable: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.field, Enum):
            self.field = str(self.field.value)

    def _pack(self, parts: list) -> dict:
        return {
            "code": self.code,
            "message": self.message,
            "field": self.field,
            "seq": to_plain(self.seq),
            "retryable": to_plain(self.retryable),
        }

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Error:
        return cls(
            h.str("code", 32, CODE_RE),
            h.str("message", 4096),
            h.str("field", 256, nullable=True),
            h.int("seq", nullable=True),
            h.bool("retryable"),
        )


@dataclass
class Heartbeat:
    TYPE: ClassVar[str] = "heartbeat"
    time: float  # sender wall clock, seconds

    def _pack(self, parts: list) -> dict:
        return {"time": to_plain(self.time)}

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Heartbeat:
        return cls(h.float("time"))


@dataclass
class Bye:
    """The end of a conversation: `kind` says why (what the peer should do), `reason` is
    free text for humans and logs."""

    TYPE: ClassVar[str] = "bye"
    reason: str = ""
    kind: ByeKind = ByeKind.LEAVING

    def _pack(self, parts: list) -> dict:
        try:
            kind = ByeKind(self.kind).value
        except ValueError:
            raise ProtocolError(
                "bad_field", f"{self.kind!r} is not one of {[k.value for k in ByeKind]}", "bye.kind"
            ) from None
        return {"kind": kind, "reason": self.reason}

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Bye:
        kind = h.str("kind", 32, choices=tuple(k.value for k in ByeKind))
        return cls(h.str("reason", 1024), ByeKind(kind))


def error_from_exception(exc: BaseException, seq: int | None = None) -> Error:
    """The Error message to send for an exception (ProtocolError keeps its code and field)."""
    if isinstance(exc, ProtocolError):
        return Error(exc.code, exc.message[:4096], exc.field, seq)
    return Error("internal", f"{type(exc).__name__}: {exc}"[:4096], None, seq)
