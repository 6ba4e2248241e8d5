"""arlight wire protocol v2: message dataclasses, encode() and decode() (spec: SPEC.md).

A message is a ZeroMQ multipart message ``[header, buffer 0, buffer 1, ...]``. The header is
a msgpack map with ``"v"`` (protocol version), ``"type"`` and the message's fields; every
image is described in the header by a descriptor (``format``, ``encoding``, ``width``,
``height``, ``step``, ``buffer`` = index of its part) and travels as its own part, so raw
numpy buffers go out zero-copy. ``"buffers"`` lists each part's byte length.

decode() is strict: any input, however hostile, either gives a valid message or raises
ProtocolError naming the field; sizes are checked against the limits before anything is
allocated. encode() runs the same header checks, so a peer never sends what it would reject.
"""

from __future__ import annotations

import dataclasses
import math
import re
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any, ClassVar, Union

import msgpack
import numpy as np

from arlight.checks import RIGID_TOLERANCE, CheckError, check_rigid

from .codecs import (
    COLOR_CODECS,
    COLOR_ENCODING,
    DEFAULT_COLOR_CODEC,
    DEFAULT_DEPTH_CODEC,
    DEFAULT_JPEG_QUALITY,
    DEFAULT_MAX_PIXELS,
    DEPTH_CODECS,
    DEPTH_ENCODING,
    MAX_IMAGE_SIDE,
    as_bytes_view,
    check_image_meta,
    decode_color,
    decode_depth,
    encode_color,
    encode_depth,
)
from .errors import ProtocolError

PROTOCOL_VERSION: int = 2  # 2: Error.retryable, Bye.kind, Result.sh_camera/diagnostics
DEFAULT_MAX_MESSAGE_BYTES: int = 64 * 2**20  # whole multipart message
MAX_HEADER_BYTES: int = 2**20  # the msgpack header part
MAX_PARTS: int = 16  # header + buffers

ROLES = ("capture", "display")
MODES = ("live", "lossless")
MAX_INT = 2**63 - 1
MAX_CREDITS = 2**20
_NAME_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
_KEY_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
_CODE_RE = re.compile(r"[a-z0-9_]{1,32}")
# a session token or the server's admin token (SPEC.md section 4, "session tokens"): the
# alphabet of secrets.token_urlsafe, 16..128 characters (at least 96 bits when random)
TOKEN_RE = re.compile(r"[A-Za-z0-9_\-]{16,128}")
TOKEN_BYTES = 24  # random bytes of a generated token: 32 characters of token_urlsafe


def new_token() -> str:
    """A random session or admin token (192 bits, URL-safe, matching TOKEN_RE)."""
    return secrets.token_urlsafe(TOKEN_BYTES)


# --------------------------------------------------------------------------- field checks


class _Map:
    """A header map being read: typed getters that name the field, unknown keys rejected."""

    def __init__(self, d: Any, name: str):
        if not isinstance(d, dict):
            raise ProtocolError("bad_field", f"expected a map, got {type(d).__name__}", name)
        self.d = d
        self.name = name
        self.seen: set[str] = set()

    def f(self, key: str) -> str:
        return f"{self.name}.{key}"

    def raw(self, key: str, nullable: bool = False) -> Any:
        self.seen.add(key)
        if key not in self.d:
            raise ProtocolError("bad_field", "missing", self.f(key))
        value = self.d[key]
        if value is None and not nullable:
            raise ProtocolError("bad_field", "must not be nil", self.f(key))
        return value

    def int(self, key: str, lo: int = 0, hi: int = MAX_INT, nullable: bool = False):
        v = self.raw(key, nullable)
        if v is None:
            return None
        if type(v) is not int:
            raise ProtocolError("bad_field", f"expected an integer, got {_tn(v)}", self.f(key))
        if not lo <= v <= hi:
            raise ProtocolError("bad_field", f"{v} is outside {lo}..{hi}", self.f(key))
        return v

    def float(self, key: str, lo: float = -math.inf, hi: float = math.inf) -> float:
        return _float(self.raw(key), self.f(key), lo, hi)

    def bool(self, key: str) -> bool:
        v = self.raw(key)
        if type(v) is not bool:
            raise ProtocolError("bad_field", f"expected a boolean, got {_tn(v)}", self.f(key))
        return v

    def str(self, key: str, max_len: int = 1024, pattern=None, choices=None, nullable=False):
        v = self.raw(key, nullable)
        if v is None:
            return None
        return _str(v, self.f(key), max_len, pattern, choices)

    def floats(self, key: str, n: int | None = None, max_len: int = 1024) -> list[float]:
        return _floats(self.raw(key), self.f(key), n, max_len)

    def map(self, key: str, nullable: bool = False) -> _Map | None:
        v = self.raw(key, nullable)
        return None if v is None else _Map(v, self.f(key))

    def done(self) -> None:
        extra = [k for k in self.d if k not in self.seen]
        if extra:
            k = extra[0]
            shown = k if isinstance(k, str) else repr(k)
            raise ProtocolError(
                "bad_field", f"unknown field {str(shown)[:64]!r}", f"{self.name}.{str(shown)[:64]}"
            )


def _tn(v: Any) -> str:
    return "nil" if v is None else type(v).__name__


def _float(v: Any, name: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if type(v) not in (int, float):
        raise ProtocolError("bad_field", f"expected a number, got {_tn(v)}", name)
    v = float(v)
    if not math.isfinite(v):
        raise ProtocolError("bad_field", f"{v} is not finite", name)
    if not lo <= v <= hi:
        raise ProtocolError("bad_field", f"{v} is outside {lo}..{hi}", name)
    return v


def _str(v: Any, name: str, max_len: int = 1024, pattern=None, choices=None) -> str:
    if type(v) is not str:
        raise ProtocolError("bad_field", f"expected a string, got {_tn(v)}", name)
    if len(v) > max_len:
        raise ProtocolError("bad_field", f"{len(v)} characters, at most {max_len}", name)
    if choices is not None and v not in choices:
        raise ProtocolError("bad_field", f"{v[:64]!r} is not one of {choices}", name)
    if pattern is not None and not pattern.fullmatch(v):
        raise ProtocolError("bad_field", f"{v[:64]!r} does not match {pattern.pattern}", name)
    return v


def _token(v: Any, name: str) -> str:
    """A token (TOKEN_RE); the message never repeats the value (it may be a near-secret)."""
    if type(v) is not str or not TOKEN_RE.fullmatch(v):
        size = f" of {len(v)} characters" if type(v) is str else ""
        raise ProtocolError("bad_field", f"not a token: expected 16..128 characters from "
                            f"A-Z a-z 0-9 _ -, got a {_tn(v)}{size}", name)
    return v


def _floats(v: Any, name: str, n: int | None = None, max_len: int = 1024) -> list[float]:
    if type(v) is not list:
        raise ProtocolError("bad_field", f"expected an array of numbers, got {_tn(v)}", name)
    if n is not None and len(v) != n:
        raise ProtocolError("bad_field", f"{len(v)} numbers, expected {n}", name)
    if len(v) > max_len:
        raise ProtocolError("bad_field", f"{len(v)} numbers, at most {max_len}", name)
    return [_float(x, f"{name}[{i}]") for i, x in enumerate(v)]


def _pose(v: Any, name: str) -> np.ndarray:
    """4 x 4 finite rigid camera-to-world matrix, rows as arrays."""
    if type(v) is not list or len(v) != 4:
        raise ProtocolError("bad_field", "expected 4 rows of 4 numbers (a 4 x 4 matrix)", name)
    rows = [_floats(r, f"{name}[{i}]", 4) for i, r in enumerate(v)]
    try:
        return check_rigid(rows, name, RIGID_TOLERANCE)  # the one rule (arlight.checks)
    except CheckError as exc:
        raise ProtocolError("bad_field", exc.message, name) from None


def _plain_value(v: Any, name: str, depth: int = 0) -> Any:
    """A msgpack scalar, or array/map of them (string keys), at most 4 levels deep."""
    if v is None or type(v) in (bool, int, float, str):
        if type(v) is str and len(v) > 4096:
            raise ProtocolError("bad_field", "string longer than 4096 characters", name)
        return v
    if depth >= 4:
        raise ProtocolError("bad_field", "nested more than 4 levels", name)
    if type(v) is list:
        if len(v) > 4096:
            raise ProtocolError("bad_field", f"{len(v)} items, at most 4096", name)
        return [_plain_value(x, f"{name}[{i}]", depth + 1) for i, x in enumerate(v)]
    if type(v) is dict:
        return _plain_map(v, name, depth + 1)
    raise ProtocolError("bad_field", f"unsupported value type {_tn(v)}", name)


def _plain_map(v: Any, name: str, depth: int = 0, max_items: int = 256) -> dict:
    if type(v) is not dict:
        raise ProtocolError("bad_field", f"expected a map, got {_tn(v)}", name)
    if len(v) > max_items:
        raise ProtocolError("bad_field", f"{len(v)} entries, at most {max_items}", name)
    out = {}
    for k, x in v.items():
        key = _str(k, f"{name} key", 64, _KEY_RE)
        out[key] = _plain_value(x, f"{name}.{key}", depth)
    return out


def _to_plain(v: Any) -> Any:
    """numpy scalars/arrays and tuples -> Python values msgpack packs (encode side)."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_to_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _to_plain(x) for k, x in v.items()}
    return v


# Result.diagnostics (SPEC.md section 4, "diagnostics"): plain values only, bounded.
DIAGNOSTICS_MAX_DEPTH = 4  # levels of maps, the diagnostics map itself being level 1
DIAGNOSTICS_MAX_KEYS = 64  # entries per map
DIAGNOSTICS_MAX_ARRAY = 1024  # numbers per array
DIAGNOSTICS_MAX_STR = 1024  # characters per string
DIAGNOSTICS_MAX_VALUES = 4096  # scalars plus array elements, in all
_DIAGNOSTIC_TYPES = "nil, bool, int, float, str, arrays of numbers and maps of these"


def plain_diagnostics(diagnostics: Any, name: str = "result.diagnostics") -> dict:
    """Result.diagnostics as the wire carries it: numpy values and tuples made plain, then
    checked against the limits; ProtocolError (bad_field, naming the key) for anything else."""
    return _read_diagnostics(_to_plain(diagnostics), name)


def _read_diagnostics(v: Any, name: str) -> dict:
    """Check a diagnostics map (decode, and encode before sending); arrays become floats."""
    budget = [DIAGNOSTICS_MAX_VALUES]
    return _diagnostics_map(v, name, 1, budget)


def _diagnostics_map(v: Any, name: str, level: int, budget: list[int]) -> dict:
    if type(v) is not dict:
        raise ProtocolError("bad_field", f"expected a map, got {_tn(v)}", name)
    if len(v) > DIAGNOSTICS_MAX_KEYS:
        raise ProtocolError(
            "bad_field", f"{len(v)} entries, at most {DIAGNOSTICS_MAX_KEYS}", name
        )
    out = {}
    for k, x in v.items():
        key = _str(k, f"{name} key", 64, _KEY_RE)
        out[key] = _diagnostics_value(x, f"{name}.{key}", level, budget)
    return out


def _diagnostics_value(x: Any, name: str, level: int, budget: list[int]) -> Any:
    t = type(x)
    if t is dict:
        if level >= DIAGNOSTICS_MAX_DEPTH:
            raise ProtocolError(
                "bad_field", f"maps nested more than {DIAGNOSTICS_MAX_DEPTH} levels deep", name
            )
        return _diagnostics_map(x, name, level + 1, budget)
    n = len(x) if t is list else 1
    budget[0] -= n
    if budget[0] < 0:
        raise ProtocolError(
            "bad_field", f"more than {DIAGNOSTICS_MAX_VALUES} values in all diagnostics", name
        )
    if t is list:
        if n > DIAGNOSTICS_MAX_ARRAY:
            raise ProtocolError(
                "bad_field", f"{n} numbers, at most {DIAGNOSTICS_MAX_ARRAY}", name
            )
        out = []
        for i, e in enumerate(x):
            if type(e) not in (int, float):
                raise ProtocolError(
                    "bad_field", f"arrays hold numbers only, got {_tn(e)}", f"{name}[{i}]"
                )
            out.append(float(e))
        return out
    if t is int and not -(2**63) <= x < 2**64:
        raise ProtocolError("bad_field", "integer outside the 64-bit range", name)
    if t is str and len(x) > DIAGNOSTICS_MAX_STR:
        raise ProtocolError(
            "bad_field", f"{len(x)} characters, at most {DIAGNOSTICS_MAX_STR}", name
        )
    if x is None or t in (bool, int, float, str):
        return x
    raise ProtocolError(
        "bad_field", f"unsupported value type {t.__name__}; diagnostics hold {_DIAGNOSTIC_TYPES}",
        name,
    )



# --------------------------------------------------------------------------- images


_COLOR_KEYS = frozenset(("format", "encoding", "width", "height", "step", "buffer", "quality"))
_DEPTH_KEYS = frozenset(("format", "encoding", "width", "height", "step", "buffer"))


class _Images:
    """Descriptors of a message's images, checked against the parts before decoding."""

    def __init__(self, parts: list[memoryview] | None, max_pixels: int, decode: bool = True):
        self.parts = parts  # None: validate descriptors only
        self.used: set[int] = set()
        self.max_pixels = max_pixels
        self.decoding = decode  # False (encode side): check the parts, decode no image

    def part(self, m: _Map, key: str) -> memoryview | None:
        """The part whose index the field `key` holds (a plain buffer index, not an image
        descriptor); each part is used by one field only. None when there are no parts."""
        index = m.raw(key)
        nbuf = MAX_PARTS - 1 if self.parts is None else len(self.parts)
        if type(index) is not int or not 0 <= index < nbuf:
            raise ProtocolError(
                "bad_field", f"buffer index {index!r} is not 0..{nbuf - 1}", m.f(key)
            )
        if index in self.used:
            raise ProtocolError("bad_field", f"buffer {index} is used twice", m.f(key))
        self.used.add(index)
        return None if self.parts is None else self.parts[index]

    def descriptor(self, m: _Map, key: str, depth: bool, nullable: bool = False):
        desc = m.raw(key, nullable)
        if desc is None:
            return None
        name = m.f(key)
        if not isinstance(desc, dict):
            raise ProtocolError("bad_field", f"expected an image descriptor, got {_tn(desc)}", name)
        allowed = _DEPTH_KEYS if depth else _COLOR_KEYS
        for k in desc:
            if k not in allowed:
                raise ProtocolError(
                    "bad_field", f"unknown field {str(k)[:64]!r}", f"{name}.{str(k)[:64]}"
                )
        if depth:
            fmt, w, h = check_image_meta(
                desc, DEPTH_CODECS, DEPTH_ENCODING, 1, 2, self.max_pixels, name
            )
        else:
            fmt, w, h = check_image_meta(
                desc, COLOR_CODECS, COLOR_ENCODING, 3, 1, self.max_pixels, name
            )
            if "quality" in desc and fmt != "jpeg":
                raise ProtocolError(
                    "bad_field", "quality is only for format jpeg", f"{name}.quality"
                )
        nbuf = MAX_PARTS - 1 if self.parts is None else len(self.parts)
        index = desc.get("buffer")
        if type(index) is not int or not 0 <= index < nbuf:
            raise ProtocolError(
                "bad_field", f"buffer index {index!r} is not 0..{nbuf - 1}", f"{name}.buffer"
            )
        if index in self.used:
            raise ProtocolError("bad_field", f"buffer {index} is used twice", f"{name}.buffer")
        self.used.add(index)
        return (desc, fmt, w, h, depth, name)

    def decode(self, d):
        if d is None or self.parts is None or not self.decoding:
            return None
        desc, _, _, _, depth, name = d
        payload = self.parts[desc["buffer"]]
        if depth:
            return decode_depth(payload, desc, max_pixels=self.max_pixels, field=name)
        return decode_color(payload, desc, max_pixels=self.max_pixels, field=name)

    def done(self, header_name: str) -> None:
        n = 0 if self.parts is None else len(self.parts)
        if self.parts is not None and len(self.used) != n:
            raise ProtocolError(
                "malformed",
                f"{n - len(self.used)} buffer(s) not used by any field",
                f"{header_name}.buffers",
            )


def _pose_to_wire(pose: Any, name: str) -> list:
    try:
        m = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise ProtocolError("bad_field", "expected a 4 x 4 matrix of numbers", name) from None
    if m.shape != (4, 4):
        raise ProtocolError("bad_field", f"expected shape (4, 4), got {m.shape}", name)
    return m.tolist()


def _add_image(parts: list, payload, meta: dict) -> dict:
    meta = dict(meta)
    meta["buffer"] = len(parts)
    parts.append(payload)
    return meta


def _float_list(v: Any, name: str) -> list:
    try:
        return np.asarray(v, dtype=np.float64).tolist()
    except (TypeError, ValueError):
        raise ProtocolError("bad_field", "expected numbers", name) from None



# --------------------------------------------------------------------------- messages
#
# One dataclass per message type. Each owns its bytes (as mcap's records.py): `_pack(parts)`
# gives the header fields (appending image payloads to `parts`) in SPEC.md's key order, and
# `_unpack(h, v, images)` reads and checks them from a header map. encode() runs `_unpack` on
# what `_pack` wrote, so a peer never sends what it would reject.


class _WireEnum(str, Enum):
    """An Enum of wire strings: members equal, print and format as their value."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


class ByeKind(_WireEnum):
    """Why a Bye was sent (its `kind` on the wire; SPEC.md section 3, "Bye")."""

    END_OF_STREAM = "end_of_stream"  # the stream ended: server -> displays, or a capture
    # client whose source has no more frames
    SHUTDOWN = "shutdown"  # the server is shutting down: reconnect to the restarted server
    LEAVING = "leaving"  # a client leaves before its stream ended (interrupted, closed)


class ErrorField(_WireEnum):
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


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole intrinsics in pixels (Foxglove CameraCalibration; K = [fx 0 cx; 0 fy cy; 0 0 1])."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = ""  # "", "plumb_bob", "rational_polynomial", ...
    D: tuple[float, ...] = ()

    def _pack(self) -> dict:
        return {
            "width": _to_plain(self.width),
            "height": _to_plain(self.height),
            "K": _to_plain([self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]),
            "distortion_model": self.distortion_model,
            "D": _to_plain(list(self.D)),
        }

    @classmethod
    def _unpack(cls, m: _Map) -> CameraCalibration:
        width = m.int("width", 1, MAX_IMAGE_SIDE)
        height = m.int("height", 1, MAX_IMAGE_SIDE)
        k = m.floats("K", 9)
        if k[1] != 0 or k[3] != 0 or k[6] != 0 or k[7] != 0 or k[8] != 1:
            raise ProtocolError(
                "bad_field", "K must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)", m.f("K")
            )
        if not (k[0] > 0 and k[4] > 0):
            raise ProtocolError(
                "bad_field", f"focal lengths must be > 0, got {k[0]}, {k[4]}", m.f("K")
            )
        model = m.str("distortion_model", 64)
        d = m.floats("D", max_len=16)
        m.done()
        return cls(width, height, k[0], k[4], k[2], k[5], model, tuple(d))


# Hello.config.scene (SPEC.md section 4, "hello: the virtual scene"): objects sent inline.
# The limits are the pipeline's (arlight.pipeline.virtual_scene MAX_OBJECTS, MAX_TRIANGLES;
# protocols does not import the pipeline, tests/test_protocols.py holds them equal). The
# bytes are bounded by the message limit (max_message_bytes), as every part is.
SCENE_MAX_OBJECTS = 64
SCENE_MAX_TRIANGLES = 2_000_000  # all objects together
SCENE_MAX_NAME = 64  # characters of an object's name
_SCENE_BUFFERS = ("vertices", "triangles", "normals")  # one part each, objects in order
_XYZ_BYTES = 12  # one vertex or normal (3 float32), or one triangle (3 uint32)
_F32 = np.dtype("<f4")
_U32 = np.dtype("<u4")


@dataclass(frozen=True)
class SceneAnchorSpec:
    """Stand the object on the support plane under `pixel` (u, v), pixels, or under the
    view's centre when None; yaw_deg: turn about the plane's up direction, degrees."""

    pixel: tuple[float, float] | None = None
    yaw_deg: float = 0.0


@dataclass(frozen=True, eq=False)
class SceneObjectSpec:
    """One virtual object as the wire carries it: plain arrays, no pipeline type (the server
    makes a `pipeline.virtual_scene.VirtualObject` of it).

    vertices: (N, 3) float32, object frame, metres; triangles: (M, 3) uint32 indices into
    vertices; normals: (N, 3) float32 unit vertex normals. Exactly one of world_from_object
    ((4, 4) float64, p_world = M [p_object, 1], rotation times a uniform scale plus a
    translation) and anchor. Material as `pipeline.virtual_scene.Material`: albedo linear RGB
    in [0, 1], roughness and metalness in [0, 1], mirror. Equality compares the arrays' values.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    world_from_object: np.ndarray | None = None
    anchor: SceneAnchorSpec | None = None
    albedo: tuple[float, float, float] = (0.7, 0.7, 0.7)
    roughness: float = 1.0
    metalness: float = 0.0
    mirror: bool = False

    __hash__ = None  # type: ignore[assignment]  # holds arrays

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SceneObjectSpec):
            return NotImplemented
        scalars = ("name", "anchor", "albedo", "roughness", "metalness", "mirror")
        if any(getattr(self, k) != getattr(other, k) for k in scalars):
            return False
        if (self.world_from_object is None) != (other.world_from_object is None):
            return False
        arrays = ("vertices", "triangles", "normals") + (
            () if self.world_from_object is None else ("world_from_object",))
        return all(np.array_equal(getattr(self, k), getattr(other, k)) for k in arrays)

    def _pack(self, name: str) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
        """The object's map and its three arrays as little-endian (N, 3) / (M, 3) arrays."""
        vertices = _xyz_array(self.vertices, _F32, f"{name}.vertices")
        triangles = _xyz_array(self.triangles, _U32, f"{name}.triangles")
        normals = _xyz_array(self.normals, _F32, f"{name}.normals")
        pose = None
        if self.world_from_object is not None:
            pose = _pose_to_wire(self.world_from_object, f"{name}.world_from_object")
            pose = [x for row in pose for x in row]
        anchor = None
        if self.anchor is not None:
            anchor = {"pixel": None if self.anchor.pixel is None else
                      _float_list(self.anchor.pixel, f"{name}.anchor.pixel"),
                      "yaw_deg": _to_plain(self.anchor.yaw_deg)}
        out = {
            "name": self.name,
            "vertex_count": len(vertices),
            "triangle_count": len(triangles),
            "world_from_object": pose,
            "anchor": anchor,
            "albedo": _float_list(self.albedo, f"{name}.albedo"),
            "roughness": _to_plain(self.roughness),
            "metalness": _to_plain(self.metalness),
            "mirror": _to_plain(self.mirror),
        }
        return out, vertices, triangles, normals


def _xyz_array(a: Any, dtype: np.dtype, name: str) -> np.ndarray:
    """An (n, 3) array of numbers as contiguous `dtype` (encode side); uint32 only from
    integers in range, so no index wraps."""
    arr = np.asarray(a)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ProtocolError("bad_field", f"expected shape (n, 3), got {arr.shape}", name)
    if dtype.kind == "u":
        if arr.dtype.kind not in "iu":
            raise ProtocolError("bad_field", f"expected integers, got {arr.dtype}", name)
        if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(np.uint32).max):
            raise ProtocolError(
                "bad_field", f"indices must lie in 0..2^32-1, got {arr.min()}..{arr.max()}", name
            )
    elif arr.dtype.kind not in "fiu":
        raise ProtocolError("bad_field", f"expected numbers, got {arr.dtype}", name)
    return np.ascontiguousarray(arr, dtype=dtype)


@dataclass(frozen=True)
class SceneSpec:
    """The virtual scene a capture client sends in its Hello (SessionConfig.scene): at most
    SCENE_MAX_OBJECTS objects with unique names, SCENE_MAX_TRIANGLES triangles in all."""

    objects: tuple[SceneObjectSpec, ...] = ()

    def _pack(self, parts: list, name: str) -> dict:
        packed = [obj._pack(f"{name}.objects[{i}]") for i, obj in enumerate(self.objects)]
        out: dict[str, Any] = {}
        for k, key in enumerate(_SCENE_BUFFERS, start=1):
            arrays = [p[k] for p in packed]
            joined = arrays[0] if len(arrays) == 1 else np.concatenate(
                arrays or [np.empty((0, 3), _U32 if key == "triangles" else _F32)])
            out[key] = len(parts)
            parts.append(memoryview(joined.reshape(-1).view(np.uint8)))
        out["objects"] = [p[0] for p in packed]
        return out

    @classmethod
    def _unpack(cls, m: _Map, images: _Images) -> SceneSpec:
        buffers = {key: images.part(m, key) for key in _SCENE_BUFFERS}
        raw = m.raw("objects")
        where = m.f("objects")
        if type(raw) is not list:
            raise ProtocolError("bad_field", f"expected an array of objects, got {_tn(raw)}",
                                where)
        if len(raw) > SCENE_MAX_OBJECTS:
            raise ProtocolError(
                "bad_field", f"{len(raw)} objects, at most {SCENE_MAX_OBJECTS}", where)
        fields, names = [], set()
        vertices_total = triangles_total = 0
        for i, o in enumerate(raw):
            om = _Map(o, f"{where}[{i}]")
            f = _scene_object_fields(om)
            if f["name"] in names:
                raise ProtocolError(
                    "bad_field", f"object name {f['name']!r} is used twice", om.f("name"))
            names.add(f["name"])
            triangles_total += f["triangle_count"]
            if triangles_total > SCENE_MAX_TRIANGLES:
                raise ProtocolError(
                    "bad_field", f"objects 0..{i} have {triangles_total} triangles together, "
                    f"at most {SCENE_MAX_TRIANGLES} in a scene; simplify the meshes",
                    om.f("triangle_count"))
            f["offsets"] = (vertices_total, triangles_total - f["triangle_count"])
            vertices_total += f["vertex_count"]
            fields.append(f)
        m.done()
        if images.parts is None:  # descriptors only: no arrays to check
            return cls()
        counts = {"vertices": vertices_total, "triangles": triangles_total,
                  "normals": vertices_total}
        for key, buf in buffers.items():
            if len(buf) != counts[key] * _XYZ_BYTES:
                what = "triangle_count" if key == "triangles" else "vertex_count"
                raise ProtocolError(
                    "bad_field", f"the part holds {len(buf)} bytes; the objects' {what}s "
                    f"({counts[key]} in all, {_XYZ_BYTES} bytes each) need "
                    f"{counts[key] * _XYZ_BYTES}", m.f(key))
        vertices = np.frombuffer(buffers["vertices"], _F32).reshape(-1, 3)
        triangles = np.frombuffer(buffers["triangles"], _U32).reshape(-1, 3)
        normals = np.frombuffer(buffers["normals"], _F32).reshape(-1, 3)
        objects = []
        for i, f in enumerate(fields):
            name = f"{where}[{i}]"
            v0, t0 = f.pop("offsets")
            nv, nt = f.pop("vertex_count"), f.pop("triangle_count")
            v, n = vertices[v0:v0 + nv], normals[v0:v0 + nv]
            t = triangles[t0:t0 + nt]
            for key, arr in (("vertices", v), ("normals", n)):
                if not np.isfinite(arr).all():
                    raise ProtocolError("bad_field", "not all finite", f"{name}.{key}")
            if t.max() >= nv:
                raise ProtocolError(
                    "bad_field", f"triangle index {int(t.max())} is outside 0..{nv - 1} "
                    f"(vertex_count {nv})", f"{name}.triangles")
            if images.decoding:  # own, aligned, native-order copies: the parts are freed
                v, t, n = v.astype(np.float32), t.astype(np.uint32), n.astype(np.float32)
            objects.append(SceneObjectSpec(vertices=v, triangles=t, normals=n, **f))
        return cls(tuple(objects))


def _scene_object_fields(om: _Map) -> dict:
    """One object's header fields, checked (its arrays are checked against the parts)."""
    name = om.str("name", SCENE_MAX_NAME)
    if not name:
        raise ProtocolError("bad_field", "must not be empty", om.f("name"))
    vertex_count = om.int("vertex_count", 3)
    triangle_count = om.int("triangle_count", 1, SCENE_MAX_TRIANGLES)
    pose = om.raw("world_from_object", nullable=True)
    if pose is not None:
        values = _floats(pose, om.f("world_from_object"), 16)
        if values[12:] != [0.0, 0.0, 0.0, 1.0]:
            raise ProtocolError(
                "bad_field", f"the last row must be 0, 0, 0, 1, got {values[12:]}",
                om.f("world_from_object"))
        pose = np.array(values, dtype=np.float64).reshape(4, 4)
    am = om.map("anchor", nullable=True)
    anchor = None
    if am is not None:
        pixel = am.raw("pixel", nullable=True)
        pixel = None if pixel is None else tuple(_floats(pixel, am.f("pixel"), 2))
        anchor = SceneAnchorSpec(pixel, am.float("yaw_deg"))
        am.done()
    if (pose is None) == (anchor is None):
        raise ProtocolError(
            "bad_field", "give exactly one of world_from_object and anchor, got "
            + ("both" if anchor is not None else "neither"),
            om.f("anchor" if anchor is not None else "world_from_object"))
    albedo = om.floats("albedo", 3)
    for k, a in enumerate(albedo):
        if not 0.0 <= a <= 1.0:
            raise ProtocolError("bad_field", f"{a} is outside 0..1 (linear RGB)",
                                f"{om.f('albedo')}[{k}]")
    out = dict(name=name, vertex_count=vertex_count, triangle_count=triangle_count,
               world_from_object=pose, anchor=anchor, albedo=tuple(albedo),
               roughness=om.float("roughness", 0.0, 1.0),
               metalness=om.float("metalness", 0.0, 1.0), mirror=om.bool("mirror"))
    om.done()
    return out


# Hello.config.exports / Result.exports (SPEC.md section 4, "engine layouts"): optional.
# The names of arlight.pipeline.engine_export.EXPORTERS (the protocol does not import the
# pipeline; tests/test_protocols.py checks the two lists agree).
EXPORT_LAYOUTS = ("arcore", "webxr", "gltf", "unity", "filament", "main_light")
MAX_FILAMENT_TEXT = 2**17  # characters: 1024 coefficients (Result.sh's limit) of ~70 each


def _read_export_names(v: Any, name: str) -> tuple[str, ...]:
    """Hello.config.exports: 1..6 distinct layout names, or nil (= none)."""
    if v is None:
        return ()
    if type(v) is not list or not 1 <= len(v) <= len(EXPORT_LAYOUTS):
        raise ProtocolError("bad_field", f"expected an array of 1..{len(EXPORT_LAYOUTS)} "
                            f"layout names, got {_tn(v)}", name)
    names = tuple(_str(x, f"{name}[{i}]", 64, choices=EXPORT_LAYOUTS) for i, x in enumerate(v))
    if len(set(names)) != len(names):
        raise ProtocolError("bad_field", f"a layout named twice: {list(names)}", name)
    return names


def _float_rows(v: Any, name: str, rows: int, cols: int) -> list[list[float]]:
    if type(v) is not list or len(v) != rows:
        raise ProtocolError("bad_field", f"expected {rows} arrays of {cols} numbers, "
                            f"got {_tn(v)}", name)
    return [_floats(r, f"{name}[{i}]", cols) for i, r in enumerate(v)]


def _read_layout(layout: str, v: Any, name: str) -> Any:
    """One engine layout's numbers, checked for shape and finiteness (SPEC.md table)."""
    if layout in ("arcore", "webxr"):
        return _floats(v, name, 27)
    if layout == "unity":
        return _float_rows(v, name, 3, 9)
    if layout == "filament":
        return _str(v, name, MAX_FILAMENT_TEXT)
    keys = {"gltf": ("intensity", "rotation", "irradianceCoefficients"),
            "main_light": ("direction", "intensity")}[layout]
    if type(v) is not dict or set(v) != set(keys):
        raise ProtocolError("bad_field", f"expected a map with keys {', '.join(keys)}, got "
                            f"{sorted(map(str, v)) if type(v) is dict else _tn(v)}", name)
    if layout == "main_light":
        return {k: _floats(v[k], f"{name}.{k}", 3) for k in keys}
    return {"intensity": _float(v["intensity"], f"{name}.intensity"),
            "rotation": _floats(v["rotation"], f"{name}.rotation", 4),
            "irradianceCoefficients": _float_rows(v["irradianceCoefficients"],
                                                  f"{name}.irradianceCoefficients", 9, 3)}


def _read_exports(v: Any, name: str) -> dict:
    """Result.exports: layout name -> that layout's numbers (each layout at most once)."""
    if type(v) is not dict or not 1 <= len(v) <= len(EXPORT_LAYOUTS):
        raise ProtocolError("bad_field", f"expected a map of 1..{len(EXPORT_LAYOUTS)} "
                            f"layouts, got {_tn(v)}", name)
    out = {}
    for k, x in v.items():
        layout = _str(k, f"{name} key", 64, choices=EXPORT_LAYOUTS)
        out[layout] = _read_layout(layout, x, f"{name}.{layout}")
    return out


# Hello.config.panorama (SPEC.md section 4, "hello: the panorama light"): optional.
LIGHT_SOURCES = ("rgbd", "panorama")
_IDENTITY_3X3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class PanoramaConfig:
    """How a session lights with the Frames' 360-degree panoramas.

    operator: the inverse tone mapping operator (the server's names, pipeline/inverse_tone.py;
    None: the server's default). light_source: which light renders the virtual objects when
    a frame has both RGB-D and a panorama, "rgbd" (the estimate) or "panorama".
    panorama_from_world: 3 x 3 rotation, row-major, d_panorama = R d_world (directions); the
    panorama's light in the world frame is its SH rotated by R^T. Identity by default.
    """

    operator: str | None = None
    light_source: str = "rgbd"
    panorama_from_world: tuple[float, ...] = _IDENTITY_3X3

    def _pack(self, name: str) -> dict:
        rotation = _float_list(self.panorama_from_world, f"{name}.panorama_from_world")
        rotation = np.asarray(rotation, dtype=np.float64).reshape(-1).tolist()
        return {"operator": self.operator, "light_source": self.light_source,
                "panorama_from_world": rotation}

    @classmethod
    def _unpack(cls, m: _Map) -> PanoramaConfig:
        operator = m.str("operator", 64, _NAME_RE, nullable=True)
        light_source = m.str("light_source", 32, choices=LIGHT_SOURCES)
        values = m.floats("panorama_from_world", 9)
        rows = [values[0:3] + [0.0], values[3:6] + [0.0], values[6:9] + [0.0],
                [0.0, 0.0, 0.0, 1.0]]
        try:
            check_rigid(rows, m.f("panorama_from_world"), RIGID_TOLERANCE)
        except CheckError:
            raise ProtocolError(
                "bad_field", f"not a rotation (orthonormal rows, determinant +1, each within "
                f"{RIGID_TOLERANCE:g}): {values}", m.f("panorama_from_world")) from None
        m.done()
        return cls(operator, light_source, tuple(values))


@dataclass
class SessionConfig:
    session: str  # session name, [A-Za-z0-9_.-]{1,64}
    client_name: str = ""
    role: str = "capture"  # "capture" | "display"
    calibration: CameraCalibration | None = None  # required for role capture
    depth_scale: float = 1000.0  # depth units per metre on the wire (TUM: 5000)
    preset: str = "full"
    overrides: dict[str, bool | int | float | str] = dataclasses.field(default_factory=dict)
    virtual_scene: str | None = None
    mode: str = "live"  # "live" | "lossless"
    want_composite: bool = False
    scene: SceneSpec | None = None  # the virtual scene itself (not with virtual_scene)
    # the panorama light (optional key); with calibration None: a panorama-only session
    panorama: PanoramaConfig | None = None
    # engine layouts (EXPORT_LAYOUTS) every Result of the session carries (optional key,
    # capture Hellos only); () = none
    exports: tuple[str, ...] = ()
    # the session token (optional key, SPEC.md "session tokens"): a display's proof that it
    # may watch the session; a capture client's token for a new session or proof for resuming
    token: str | None = None

    def _pack(self, parts: list) -> dict:
        out = {
            "session": self.session,
            "client_name": self.client_name,
            "role": self.role,
            "calibration": None if self.calibration is None else self.calibration._pack(),
            "depth_scale": _to_plain(self.depth_scale),
            "preset": self.preset,
            "overrides": _to_plain(self.overrides),
            "virtual_scene": self.virtual_scene,
            "mode": self.mode,
            "want_composite": _to_plain(self.want_composite),
        }
        if self.scene is not None:  # optional key: absent when there is no scene
            out["scene"] = self.scene._pack(parts, "hello.config.scene")
        if self.panorama is not None:  # optional key: absent when the session has none
            out["panorama"] = self.panorama._pack("hello.config.panorama")
        if self.exports:  # optional key: absent when the session asks for no layout
            out["exports"] = list(_read_export_names(list(self.exports),
                                                     "hello.config.exports"))
            _exports_role(self.role, "hello.config.exports")
        if self.token is not None:  # optional key: absent when the client has no token
            out["token"] = _token(self.token, "hello.config.token")
        return out

    @classmethod
    def _unpack(cls, c: _Map, images: _Images) -> SessionConfig:
        session = c.str("session", 64, _NAME_RE)
        client_name = c.str("client_name", 128)
        role = c.str("role", choices=ROLES)
        cal = c.map("calibration", nullable=True)
        calibration = None if cal is None else CameraCalibration._unpack(cal)
        panorama = None
        if "panorama" in c.d:  # optional key (SPEC.md section 2): absent = nil
            pm = c.map("panorama", nullable=True)
            panorama = None if pm is None else PanoramaConfig._unpack(pm)
        if role == "capture" and calibration is None and panorama is None:
            raise ProtocolError("bad_field", "required for role capture (nil only for a "
                                "panorama-only session: give config.panorama)",
                                c.f("calibration"))
        depth_scale = c.float("depth_scale", 1e-6, 1e9)
        preset = c.str("preset", 64, _NAME_RE)
        overrides = _read_overrides(c.raw("overrides"), c.f("overrides"))
        virtual_scene = c.str("virtual_scene", 1024, nullable=True)
        mode = c.str("mode", choices=MODES)
        want_composite = c.bool("want_composite")
        scene = None
        if "scene" in c.d:  # the one optional key (SPEC.md section 2): absent = nil
            sm = c.map("scene", nullable=True)
            scene = None if sm is None else SceneSpec._unpack(sm, images)
        if scene is not None and virtual_scene is not None:
            raise ProtocolError(
                "bad_field", f"give virtual_scene (a built-in scene name, here "
                f"{virtual_scene[:64]!r}) or scene (the scene itself), not both", c.f("scene"))
        exports: tuple[str, ...] = ()
        if "exports" in c.d:  # optional key: absent = nil = none
            exports = _read_export_names(c.raw("exports", nullable=True), c.f("exports"))
            if exports:
                _exports_role(role, c.f("exports"))
        token = None
        if "token" in c.d:  # optional key (SPEC.md section 2): absent = nil
            raw = c.raw("token", nullable=True)
            token = None if raw is None else _token(raw, c.f("token"))
        c.done()
        return cls(session, client_name, role, calibration, depth_scale, preset, overrides,
                   virtual_scene, mode, want_composite, scene, panorama, exports, token)


def _exports_role(role: str, name: str) -> None:
    """The layouts are the session's: the capture client's Hello chooses them."""
    if role != "capture":
        raise ProtocolError("bad_field", "only a capture Hello chooses the session's engine "
                            "layouts (a display receives them in every Result, or computes "
                            "its own: arlight display --export)", name)


def _read_overrides(v: Any, name: str) -> dict[str, bool | int | float | str]:
    """Config overrides: <= 256 entries, name -> bool, int, finite float or str <= 4096."""
    if type(v) is not dict:
        raise ProtocolError("bad_field", f"expected a map, got {_tn(v)}", name)
    if len(v) > 256:
        raise ProtocolError("bad_field", f"{len(v)} entries, at most 256", name)
    out: dict[str, bool | int | float | str] = {}
    for k, x in v.items():
        key = _str(k, f"{name} key", 64, _KEY_RE)
        if type(x) not in (bool, int, float, str):
            raise ProtocolError(
                "bad_field", f"expected bool, int, float or string, got {_tn(x)}", f"{name}.{key}"
            )
        if type(x) is float and not math.isfinite(x):
            raise ProtocolError("bad_field", f"{x} is not finite", f"{name}.{key}")
        if type(x) is str and len(x) > 4096:
            raise ProtocolError("bad_field", "string longer than 4096 characters", f"{name}.{key}")
        out[key] = x
    return out


@dataclass
class Hello:
    TYPE: ClassVar[str] = "hello"
    protocol_version: int
    config: SessionConfig

    def _pack(self, parts: list) -> dict:
        return {"config": self.config._pack(parts)}

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Hello:
        return cls(v, SessionConfig._unpack(h.map("config"), images))


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
            "credits": _to_plain(self.credits),
            "heartbeat_interval_s": _to_plain(self.heartbeat_interval_s),
            "server_name": self.server_name,
        }
        if self.token is not None:  # optional key: absent when no token is told
            out["token"] = _token(self.token, "welcome.token")
        return out

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Welcome:
        raw = h.raw("token", nullable=True) if "token" in h.d else None
        token = None if raw is None else _token(raw, h.f("token"))
        return cls(
            v,
            h.str("session", 64, _NAME_RE),
            h.int("credits", 0, MAX_CREDITS),
            h.float("heartbeat_interval_s", 1e-3, 3600.0),
            h.str("server_name", 128),
            token,
        )


@dataclass
class Frame:
    TYPE: ClassVar[str] = "frame"
    seq: int  # >= 0, per session, increasing
    timestamp: float  # capture time, sender clock, seconds
    color: np.ndarray | None  # (H, W, 3) uint8 RGB; None with depth: a panorama-only frame
    depth: np.ndarray | None  # (H, W) uint16, SessionConfig.depth_scale units per metre,
    # 0 = missing; None together with color (then panorama is required)
    pose: np.ndarray | None = None  # (4, 4) float64 camera-to-world
    panorama: np.ndarray | None = None  # (h, w, 3) uint8 RGB equirectangular
    color_codec: str = DEFAULT_COLOR_CODEC  # also used for the panorama
    depth_codec: str = DEFAULT_DEPTH_CODEC
    jpeg_quality: int = DEFAULT_JPEG_QUALITY

    def _pack(self, parts: list) -> dict:
        nm = "frame"
        color, depth = self.color, self.depth
        if isinstance(color, np.ndarray) and isinstance(depth, np.ndarray):
            if color.shape[:2] != depth.shape[:2]:
                raise ProtocolError(
                    "bad_field",
                    f"depth shape {depth.shape} and colour shape {color.shape} must agree in "
                    "(H, W)",
                    f"{nm}.depth",
                )
        out: dict[str, Any] = {
            "seq": _to_plain(self.seq),
            "timestamp": _to_plain(self.timestamp),
            "pose": None if self.pose is None else _pose_to_wire(self.pose, f"{nm}.pose"),
        }
        if (color is None) != (depth is None):
            missing = "color" if color is None else "depth"
            raise ProtocolError("bad_field", "give both colour and depth, or neither (a "
                                "panorama-only frame)", f"{nm}.{missing}")
        if color is None and self.panorama is None:
            raise ProtocolError("bad_field", "a frame without colour and depth must carry a "
                                "panorama", f"{nm}.panorama")
        out["color"] = None if color is None else _add_image(
            parts, *encode_color(color, self.color_codec, self.jpeg_quality, field=f"{nm}.color")
        )
        out["depth"] = None if depth is None else _add_image(
            parts, *encode_depth(depth, self.depth_codec, field=f"{nm}.depth")
        )
        out["panorama"] = None if self.panorama is None else _add_image(
            parts,
            *encode_color(self.panorama, self.color_codec, self.jpeg_quality,
                          field=f"{nm}.panorama"),
        )
        return out

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Frame:
        seq = h.int("seq")
        timestamp = h.float("timestamp")
        pose = h.raw("pose", nullable=True)
        pose = None if pose is None else _pose(pose, h.f("pose"))
        dc = images.descriptor(h, "color", depth=False, nullable=True)
        dd = images.descriptor(h, "depth", depth=True, nullable=True)
        dp = images.descriptor(h, "panorama", depth=False, nullable=True)
        if (dc is None) != (dd is None):
            raise ProtocolError("bad_field", "give both colour and depth, or neither (a "
                                "panorama-only frame)", h.f("color" if dc is None else "depth"))
        if dc is None and dp is None:
            raise ProtocolError("bad_field", "a frame without colour and depth must carry a "
                                "panorama", h.f("panorama"))
        if dc is not None and (dc[2], dc[3]) != (dd[2], dd[3]):
            raise ProtocolError(
                "bad_field",
                f"depth is {dd[2]} x {dd[3]}, colour {dc[2]} x {dc[3]}: they must agree",
                h.f("depth"),
            )
        h.done()
        images.done(h.name)
        color = images.decode(dc)
        depth = images.decode(dd)
        panorama = images.decode(dp)
        first = dc if dc is not None else dp  # the colour codec: of the colour, else panorama
        quality = first[0].get("quality", DEFAULT_JPEG_QUALITY)
        depth_codec = DEFAULT_DEPTH_CODEC if dd is None else dd[1]
        return cls(seq, timestamp, color, depth, pose, panorama, first[1], depth_codec, quality)


@dataclass(kw_only=True)
class Result:
    """The lighting of one processed frame (server -> capture and display clients).

    Built with keywords only. `diagnostics`: a bounded map of plain values (str, bool, int,
    float, nil, arrays of numbers, maps of these; SPEC.md "diagnostics"), e.g. the pipeline's
    `{"tracking": {"ok": True, "reason": ""}}`; anything else is refused by encode().
    """

    TYPE: ClassVar[str] = "result"
    seq: int
    timestamp: float  # the frame's capture timestamp, sender clock, seconds
    sh: list[float]  # radiance SH, luminance, world frame, L^2 coefficients
    sh_camera: list[float] | None = None  # the same light in this frame's camera frame
    sh_rgb: list[list[float]] | None = None  # 3 x L^2, world frame
    dominant_direction_camera: list[float]  # unit vector towards the light
    dominant_direction_world: list[float]
    intensity: float
    confidence: dict
    pose: list[list[float]]  # 4 x 4 camera-to-world
    timings_ms: dict[str, float]
    diagnostics: dict = dataclasses.field(default_factory=dict)
    frames_received: int  # session counters so far
    frames_processed: int
    frames_dropped: int
    server_receive_time: float  # server wall clock, seconds
    server_finish_time: float
    composite: np.ndarray | None = None  # (H, W, 3) uint8 RGB
    composite_codec: str = "jpeg"
    jpeg_quality: int = DEFAULT_JPEG_QUALITY
    # the frame's panorama light (optional keys, all three or none: absent = no panorama),
    # in the PANORAMA's frame (+y up, u = atan2(x, -z) / 2 pi), radiance of the HDR map
    panorama_sh: list[float] | None = None  # luminance, L^2 coefficients
    panorama_sh_rgb: list[list[float]] | None = None  # 3 x L^2, linear R, G, B
    panorama_dominant_direction: list[float] | None = None  # unit, towards the light
    # the light in the engine layouts the session's Hello asked for (optional key: absent
    # when it asked for none): layout name -> numbers, CAMERA frame with the engine's axes
    exports: dict | None = None

    def _pack(self, parts: list) -> dict:
        out = {
            "seq": _to_plain(self.seq),
            "timestamp": _to_plain(self.timestamp),
            "sh": _float_list(self.sh, "result.sh"),
            "sh_camera": None if self.sh_camera is None else _float_list(
                self.sh_camera, "result.sh_camera"),
            "sh_rgb": None if self.sh_rgb is None else _float_list(self.sh_rgb, "result.sh_rgb"),
            "dominant_direction_camera": _float_list(
                self.dominant_direction_camera, "result.dominant_direction_camera"
            ),
            "dominant_direction_world": _float_list(
                self.dominant_direction_world, "result.dominant_direction_world"
            ),
            "intensity": _to_plain(self.intensity),
            "confidence": _to_plain(self.confidence),
            "pose": _pose_to_wire(self.pose, "result.pose"),
            "timings_ms": _to_plain(self.timings_ms),
            "diagnostics": _to_plain(self.diagnostics),
            "frames_received": _to_plain(self.frames_received),
            "frames_processed": _to_plain(self.frames_processed),
            "frames_dropped": _to_plain(self.frames_dropped),
            "server_receive_time": _to_plain(self.server_receive_time),
            "server_finish_time": _to_plain(self.server_finish_time),
        }
        given = [self.panorama_sh is not None, self.panorama_sh_rgb is not None,
                 self.panorama_dominant_direction is not None]
        if any(given) and not all(given):
            missing = [k for k, g in zip(_PANORAMA_RESULT_KEYS, given, strict=True) if not g]
            raise ProtocolError("bad_field", "give panorama_sh, panorama_sh_rgb and "
                                "panorama_dominant_direction together, or none",
                                f"result.{missing[0]}")
        if all(given):  # optional keys: absent when the frame had no panorama
            out["panorama_sh"] = _float_list(self.panorama_sh, "result.panorama_sh")
            out["panorama_sh_rgb"] = _float_list(self.panorama_sh_rgb, "result.panorama_sh_rgb")
            out["panorama_dominant_direction"] = _float_list(
                self.panorama_dominant_direction, "result.panorama_dominant_direction")
        if self.exports is not None:  # optional key: absent when the session asked for none
            out["exports"] = _read_exports(_to_plain(self.exports), "result.exports")
        out["composite"] = None
        if self.composite is not None:
            out["composite"] = _add_image(
                parts,
                *encode_color(self.composite, self.composite_codec, self.jpeg_quality,
                              field="result.composite"),
            )
        return out

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Result:
        seq = h.int("seq")
        timestamp = h.float("timestamp")
        sh = h.floats("sh", max_len=1024)
        bands = math.isqrt(len(sh))
        if not sh or bands * bands != len(sh):
            raise ProtocolError(
                "bad_field", f"{len(sh)} coefficients is not L^2 for L >= 1", h.f("sh")
            )
        sh_camera = h.raw("sh_camera", nullable=True)
        if sh_camera is not None:
            sh_camera = _floats(sh_camera, h.f("sh_camera"), len(sh))
        sh_rgb = h.raw("sh_rgb", nullable=True)
        if sh_rgb is not None:
            if type(sh_rgb) is not list or len(sh_rgb) != 3:
                raise ProtocolError(
                    "bad_field", "expected 3 arrays (R, G, B) of L^2 numbers", h.f("sh_rgb")
                )
            sh_rgb = [_floats(c, f"{h.f('sh_rgb')}[{i}]", len(sh)) for i, c in enumerate(sh_rgb)]
        fields: dict[str, Any] = dict(
            seq=seq, timestamp=timestamp, sh=sh, sh_camera=sh_camera, sh_rgb=sh_rgb,
            dominant_direction_camera=h.floats("dominant_direction_camera", 3),
            dominant_direction_world=h.floats("dominant_direction_world", 3),
            intensity=h.float("intensity"),
            confidence=_plain_map(h.raw("confidence"), h.f("confidence"), 0, 64),
            pose=_pose(h.raw("pose"), h.f("pose")).tolist(),
        )
        timings = _plain_map(h.raw("timings_ms"), h.f("timings_ms"), 0, 64)
        fields["timings_ms"] = {
            k: _float(x, f"{h.f('timings_ms')}.{k}", 0.0) for k, x in timings.items()
        }
        fields["diagnostics"] = _read_diagnostics(h.raw("diagnostics"), h.f("diagnostics"))
        for key in ("frames_received", "frames_processed", "frames_dropped"):
            fields[key] = h.int(key)
        for key in ("server_receive_time", "server_finish_time"):
            fields[key] = h.float(key)
        fields.update(_read_panorama_light(h))
        if "exports" in h.d:  # optional key: absent = the session asked for no layout
            fields["exports"] = _read_exports(h.raw("exports"), h.f("exports"))
        dc = images.descriptor(h, "composite", depth=False, nullable=True)
        h.done()
        images.done(h.name)
        if dc is not None:
            fields.update(composite=images.decode(dc), composite_codec=dc[1],
                          jpeg_quality=dc[0].get("quality", DEFAULT_JPEG_QUALITY))
        return cls(**fields)


_PANORAMA_RESULT_KEYS = ("panorama_sh", "panorama_sh_rgb", "panorama_dominant_direction")


def _read_panorama_light(h: _Map) -> dict:
    """Result's optional panorama keys: all three or none (SPEC.md, "result")."""
    present = [k in h.d for k in _PANORAMA_RESULT_KEYS]
    if not any(present):
        return {}
    if not all(present):
        missing = _PANORAMA_RESULT_KEYS[present.index(False)]
        raise ProtocolError("bad_field", "missing (the panorama keys come all three or none)",
                            h.f(missing))
    coeffs = h.floats("panorama_sh", max_len=1024)
    bands = math.isqrt(len(coeffs))
    if not coeffs or bands * bands != len(coeffs):
        raise ProtocolError(
            "bad_field", f"{len(coeffs)} coefficients is not L^2 for L >= 1", h.f("panorama_sh"))
    rgb = h.raw("panorama_sh_rgb")
    if type(rgb) is not list or len(rgb) != 3:
        raise ProtocolError("bad_field", "expected 3 arrays (R, G, B) of L^2 numbers",
                            h.f("panorama_sh_rgb"))
    rgb = [_floats(c, f"{h.f('panorama_sh_rgb')}[{i}]", len(coeffs)) for i, c in enumerate(rgb)]
    direction = h.floats("panorama_dominant_direction", 3)
    return {"panorama_sh": coeffs, "panorama_sh_rgb": rgb,
            "panorama_dominant_direction": direction}


@dataclass
class Credit:
    TYPE: ClassVar[str] = "credit"
    credits: int  # lossless flow control: capture may send this many more frames

    def _pack(self, parts: list) -> dict:
        return {"credits": _to_plain(self.credits)}

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Credit:
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
        return {"code": self.code, "message": self.message, "field": self.field,
                "seq": _to_plain(self.seq), "retryable": _to_plain(self.retryable)}

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Error:
        return cls(
            h.str("code", 32, _CODE_RE),
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
        return {"time": _to_plain(self.time)}

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Heartbeat:
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
                "bad_field", f"{self.kind!r} is not one of {[k.value for k in ByeKind]}",
                "bye.kind") from None
        return {"kind": kind, "reason": self.reason}

    @classmethod
    def _unpack(cls, h: _Map, v: int, images: _Images) -> Bye:
        kind = h.str("kind", 32, choices=tuple(k.value for k in ByeKind))
        return cls(h.str("reason", 1024), ByeKind(kind))


Message = Union[Hello, Welcome, Frame, Result, Credit, Error, Heartbeat, Bye]  # noqa: UP007

MESSAGE_TYPES: dict[str, type] = {
    cls.TYPE: cls for cls in (Hello, Welcome, Frame, Result, Credit, Error, Heartbeat, Bye)
}
_TYPE_NAMES = {cls: name for name, cls in MESSAGE_TYPES.items()}


def error_from_exception(exc: BaseException, seq: int | None = None) -> Error:
    """The Error message to send for an exception (ProtocolError keeps its code and field)."""
    if isinstance(exc, ProtocolError):
        return Error(exc.code, exc.message[:4096], exc.field, seq)
    return Error("internal", f"{type(exc).__name__}: {exc}"[:4096], None, seq)



# --------------------------------------------------------------------------- encode / decode


def encode(
    msg: Message,
    *,
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_pixels: int = DEFAULT_MAX_PIXELS,
) -> list[bytes | memoryview]:
    """Multipart ZeroMQ frames ``[msgpack header, buffer 0, ...]``; raw images zero-copy.

    Raises ProtocolError (``bad_field``, ``bad_codec``, ``too_large``) for a message that
    decode() would reject. Send with ``socket.send_multipart(parts, copy=False)``.
    """
    name = _TYPE_NAMES.get(type(msg))
    if name is None:
        raise ProtocolError("unknown_type", f"{type(msg).__name__} is not a protocol message")
    version = msg.protocol_version if name in ("hello", "welcome") else PROTOCOL_VERSION
    parts: list[bytes | memoryview] = []
    header: dict[str, Any] = {"v": _to_plain(version), "type": name}
    header.update(msg._pack(parts))
    if parts:
        header["buffers"] = [len(as_bytes_view(p)) for p in parts]
    if version != PROTOCOL_VERSION:  # a deliberately wrong version (tests); skip the checks
        return [msgpack.packb(header, use_bin_type=True), *parts]
    m = _Map(header, name)
    m.seen.update(("v", "type", "buffers"))
    images = _Images([as_bytes_view(p) for p in parts], max_pixels, decode=False)
    type(msg)._unpack(m, version, images)
    m.done()
    images.done(name)
    try:
        packed = msgpack.packb(header, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:  # pragma: no cover - checked above
        raise ProtocolError("bad_field", f"cannot pack header: {exc}", name) from None
    total = len(packed) + sum(header.get("buffers", ()))
    if len(packed) > MAX_HEADER_BYTES:
        raise ProtocolError(
            "too_large", f"header of {len(packed)} bytes exceeds {MAX_HEADER_BYTES}", name
        )
    if total > max_message_bytes:
        raise ProtocolError(
            "too_large",
            f"message of {total} bytes exceeds max_message_bytes {max_message_bytes}",
            name,
        )
    return [packed, *parts]


def _views(parts: Any) -> list[memoryview]:
    if isinstance(parts, (bytes, bytearray, memoryview, str)) or not isinstance(parts, Sequence):
        raise ProtocolError("malformed", "expected a sequence of message parts")
    if not parts:
        raise ProtocolError("malformed", "empty multipart message")
    if len(parts) > MAX_PARTS:
        raise ProtocolError("malformed", f"{len(parts)} parts, at most {MAX_PARTS}")
    return [as_bytes_view(p) for p in parts]


def _header(view: memoryview) -> dict:
    if len(view) > MAX_HEADER_BYTES:
        raise ProtocolError(
            "too_large", f"header of {len(view)} bytes exceeds {MAX_HEADER_BYTES}", "header"
        )
    try:
        header = msgpack.unpackb(view, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises many types for bad input
        raise ProtocolError(
            "malformed", f"header is not msgpack: {type(exc).__name__}: {str(exc)[:200]}", "header"
        ) from None
    if type(header) is not dict:
        raise ProtocolError(
            "malformed", f"header is a msgpack {_tn(header)}, expected a map", "header"
        )
    v = header.get("v")
    if type(v) is not int:
        raise ProtocolError(
            "malformed", f"header field v (protocol version) is {_tn(v)}, expected an integer", "v"
        )
    if v != PROTOCOL_VERSION:
        raise ProtocolError(
            "bad_version", f"protocol version {v}, this peer speaks {PROTOCOL_VERSION}", "v"
        )
    t = header.get("type")
    if type(t) is not str:
        raise ProtocolError(
            "malformed", f"header field type is {_tn(t)}, expected a string", "type"
        )
    if t not in MESSAGE_TYPES:
        raise ProtocolError(
            "unknown_type", f"message type {t[:64]!r} is not one of {tuple(MESSAGE_TYPES)}", "type"
        )
    return header


def peek_header(parts: Any) -> dict:
    """The msgpack header (a map with a valid "v" and "type"), without decoding any image."""
    return _header(_views(parts)[0])


def decode(
    parts: Sequence[Any],
    *,
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_pixels: int = DEFAULT_MAX_PIXELS,
) -> Message:
    """Decode a multipart message; raises ProtocolError (never anything else) naming the field."""
    try:
        return _decode(parts, max_message_bytes, max_pixels)
    except ProtocolError:
        raise
    except Exception as exc:  # a bug or an input we did not foresee: still a ProtocolError
        raise ProtocolError("malformed", f"{type(exc).__name__}: {str(exc)[:200]}") from exc


def _decode(parts: Any, max_message_bytes: int, max_pixels: int) -> Message:
    views = _views(parts)
    total = sum(len(p) for p in views)
    if total > max_message_bytes:
        raise ProtocolError(
            "too_large", f"message of {total} bytes exceeds max_message_bytes {max_message_bytes}"
        )
    header = _header(views[0])
    name = header["type"]
    bufs = views[1:]
    declared = header.get("buffers", [])
    if type(declared) is not list or any(type(n) is not int for n in declared):
        raise ProtocolError(
            "malformed", "buffers must be an array of byte lengths", f"{name}.buffers"
        )
    if len(declared) != len(bufs):
        raise ProtocolError(
            "malformed",
            f"header declares {len(declared)} buffer(s), the "
            f"message has {len(bufs)} part(s) after the header",
            f"{name}.buffers",
        )
    for i, (n, b) in enumerate(zip(declared, bufs, strict=True)):
        if n != len(b):
            raise ProtocolError(
                "malformed",
                f"buffer {i} is {len(b)} bytes, the header declares {n}",
                f"{name}.buffers[{i}]",
            )
    m = _Map(header, name)
    m.seen.update(("v", "type", "buffers"))
    images = _Images(bufs, max_pixels)
    msg = MESSAGE_TYPES[name]._unpack(m, header["v"], images)
    m.done()
    images.done(name)
    return msg
