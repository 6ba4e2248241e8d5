"""The one error type of the wire protocol."""

from __future__ import annotations

ERROR_CODES: tuple[str, ...] = (
    "malformed",  # not a message: bad msgpack, wrong part count, part length disagrees
    "bad_version",  # header "v" is not PROTOCOL_VERSION
    "unknown_type",  # header "type" names no message
    "bad_field",  # a field is missing, has the wrong type or is outside its limits
    "too_large",  # a declared size is over a limit (checked before anything is allocated)
    "bad_codec",  # unknown image format or pixel encoding
    "decode_failed",  # a payload does not decode to exactly the declared image
    "bad_state",  # a valid message at the wrong time (used by the server's session logic)
    "unauthorized",  # a Hello without the session's token (or the admin token): refused
    "over_budget",  # settings or data over the server's time or memory budget (server only)
    "deadline",  # a frame abandoned past the server's per-frame deadline (server only)
)


class ProtocolError(ValueError):
    """A message or payload that breaks the wire protocol.

    ``code`` is one of ``ERROR_CODES``; ``field`` is the dotted name of the offending field
    (``"frame.depth.height"``) or None; ``message`` says what was expected and what came.
    """

    def __init__(self, code: str, message: str, field: str | None = None):
        self.code = code
        self.message = message
        self.field = field
        where = f" [{field}]" if field else ""
        super().__init__(f"{code}{where}: {message}")

    def __reduce__(self):  # picklable with its fields (multiprocessing, logging handlers)
        return (type(self), (self.code, self.message, self.field))
