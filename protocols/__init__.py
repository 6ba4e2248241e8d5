"""arlight.protocols: the wire protocol (messages, image codecs, validation). Spec: SPEC.md.

One module per concern: fields.py (version, limits, the schema reader), images.py and
codecs.py (image descriptors, pixel codecs), session_config.py with scene.py and layouts.py
(Hello), frame_result.py (Frame, Result), control.py (Welcome, Credit, Error, Heartbeat, Bye),
diagnostics.py, wire.py (encode/decode of the multipart framing), errors.py, container.py,
records.py. messages.py re-exports the messages for code that imports it by that name.
"""

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
from .control import (
    Bye,
    ByeKind,
    Credit,
    Error,
    ErrorField,
    Heartbeat,
    Welcome,
    error_from_exception,
)
from .diagnostics import plain_diagnostics
from .errors import ERROR_CODES, ProtocolError
from .fields import (
    DEFAULT_MAX_MESSAGE_BYTES,
    MAX_HEADER_BYTES,
    MODES,
    PROTOCOL_VERSION,
    ROLES,
    TOKEN_RE,
    new_token,
)
from .frame_result import Frame, Result
from .layouts import EXPORT_LAYOUTS
from .records import received_record, result_record
from .scene import (
    SCENE_MAX_OBJECTS,
    SCENE_MAX_TRIANGLES,
    SceneAnchorSpec,
    SceneObjectSpec,
    SceneSpec,
)
from .session_config import LIGHT_SOURCES, CameraCalibration, Hello, PanoramaConfig, SessionConfig
from .wire import MESSAGE_TYPES, Message, decode, encode, peek_header

__all__ = [
    "COLOR_CODECS",
    "DEFAULT_COLOR_CODEC",
    "DEFAULT_DEPTH_CODEC",
    "LIGHT_SOURCES",
    "DEFAULT_JPEG_QUALITY",
    "DEFAULT_MAX_MESSAGE_BYTES",
    "DEFAULT_MAX_PIXELS",
    "DEPTH_CODECS",
    "EXPORT_LAYOUTS",
    "ERROR_CODES",
    "MAX_HEADER_BYTES",
    "MESSAGE_TYPES",
    "MODES",
    "PROTOCOL_VERSION",
    "ROLES",
    "TOKEN_RE",
    "new_token",
    "SCENE_MAX_OBJECTS",
    "SCENE_MAX_TRIANGLES",
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
    "PanoramaConfig",
    "Result",
    "SceneAnchorSpec",
    "SceneObjectSpec",
    "SceneSpec",
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
