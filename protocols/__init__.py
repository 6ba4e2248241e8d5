"""arlight.protocols: the wire protocol (messages, image codecs, validation). Spec: SPEC.md."""

from .codecs import (
    COLOR_CODECS,
    DEFAULT_COLOR_CODEC,
    DEFAULT_DEPTH_CODEC,
    DEFAULT_JPEG_QUALITY,
    DEFAULT_MAX_PIXELS,
    DEPTH_CODECS,
    decode_color,
    decode_depth,
    encode_color,
    encode_depth,
)
from .container import read_container, write_container
from .errors import ERROR_CODES, ProtocolError
from .messages import (
    DEFAULT_MAX_MESSAGE_BYTES,
    MAX_HEADER_BYTES,
    MESSAGE_TYPES,
    MODES,
    PROTOCOL_VERSION,
    ROLES,
    Bye,
    ByeKind,
    CameraCalibration,
    Credit,
    Error,
    ErrorField,
    Frame,
    Heartbeat,
    Hello,
    Message,
    Result,
    SessionConfig,
    Welcome,
    decode,
    encode,
    error_from_exception,
    peek_header,
    plain_diagnostics,
)
from .records import received_record, result_record

__all__ = [
    "COLOR_CODECS",
    "DEFAULT_COLOR_CODEC",
    "DEFAULT_DEPTH_CODEC",
    "DEFAULT_JPEG_QUALITY",
    "DEFAULT_MAX_MESSAGE_BYTES",
    "DEFAULT_MAX_PIXELS",
    "DEPTH_CODECS",
    "ERROR_CODES",
    "MAX_HEADER_BYTES",
    "MESSAGE_TYPES",
    "MODES",
    "PROTOCOL_VERSION",
    "ROLES",
    "Bye",
    "ByeKind",
    "CameraCalibration",
    "Credit",
    "Error",
    "ErrorField",
    "Frame",
    "Heartbeat",
    "Hello",
    "Message",
    "ProtocolError",
    "Result",
    "SessionConfig",
    "Welcome",
    "decode",
    "decode_color",
    "decode_depth",
    "encode",
    "encode_color",
    "encode_depth",
    "error_from_exception",
    "peek_header",
    "plain_diagnostics",
    "received_record",
    "result_record",
    "read_container",
    "rvl_decode",
    "rvl_encode",
    "write_container",
]


def __getattr__(name: str):  # rvl_encode / rvl_decode load numba on first use, not at import
    if name in ("rvl_encode", "rvl_decode"):
        from . import rvl

        return getattr(rvl, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
