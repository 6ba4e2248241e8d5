"""The protocol's messages, by their former single module: a re-export, kept so that
`from arlight.protocols.messages import X` goes on working. New code imports from
`arlight.protocols` (the package) or from the module of the concern:

- fields.py: the version, the limits, name and token patterns, the schema reader;
- diagnostics.py: Result.diagnostics and its limits;
- images.py: image descriptors (the pixel codecs: codecs.py);
- scene.py: the virtual scene of a Hello; layouts.py: the engine layouts;
- session_config.py: Hello, SessionConfig, CameraCalibration, PanoramaConfig;
- frame_result.py: Frame and Result;
- control.py: Welcome, Credit, Error, Heartbeat, Bye, ByeKind, ErrorField;
- wire.py: encode, decode, peek_header, MESSAGE_TYPES (the multipart framing).
"""

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
from .diagnostics import (
    DIAGNOSTICS_MAX_ARRAY,
    DIAGNOSTICS_MAX_DEPTH,
    DIAGNOSTICS_MAX_KEYS,
    DIAGNOSTICS_MAX_STR,
    DIAGNOSTICS_MAX_VALUES,
    plain_diagnostics,
)
from .fields import (
    DEFAULT_MAX_MESSAGE_BYTES,
    MAX_CREDITS,
    MAX_HEADER_BYTES,
    MAX_INT,
    MAX_PARTS,
    MODES,
    PROTOCOL_VERSION,
    ROLES,
    TOKEN_BYTES,
    TOKEN_RE,
    new_token,
)
from .frame_result import Frame, Result
from .layouts import EXPORT_LAYOUTS, MAX_FILAMENT_TEXT
from .scene import (
    SCENE_MAX_NAME,
    SCENE_MAX_OBJECTS,
    SCENE_MAX_TRIANGLES,
    SceneAnchorSpec,
    SceneObjectSpec,
    SceneSpec,
)
from .session_config import LIGHT_SOURCES, CameraCalibration, Hello, PanoramaConfig, SessionConfig
from .wire import MESSAGE_TYPES, Message, decode, encode, peek_header

__all__ = [
    "DEFAULT_MAX_MESSAGE_BYTES",
    "DIAGNOSTICS_MAX_ARRAY",
    "DIAGNOSTICS_MAX_DEPTH",
    "DIAGNOSTICS_MAX_KEYS",
    "DIAGNOSTICS_MAX_STR",
    "DIAGNOSTICS_MAX_VALUES",
    "EXPORT_LAYOUTS",
    "LIGHT_SOURCES",
    "MAX_CREDITS",
    "MAX_FILAMENT_TEXT",
    "MAX_HEADER_BYTES",
    "MAX_INT",
    "MAX_PARTS",
    "MESSAGE_TYPES",
    "MODES",
    "PROTOCOL_VERSION",
    "ROLES",
    "SCENE_MAX_NAME",
    "SCENE_MAX_OBJECTS",
    "SCENE_MAX_TRIANGLES",
    "TOKEN_BYTES",
    "TOKEN_RE",
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
    "PanoramaConfig",
    "Result",
    "SceneAnchorSpec",
    "SceneObjectSpec",
    "SceneSpec",
    "SessionConfig",
    "Welcome",
    "decode",
    "encode",
    "error_from_exception",
    "new_token",
    "peek_header",
    "plain_diagnostics",
]
