"""arlight wire protocol v1: message dataclasses, encode() and decode() (spec: SPEC.md).

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

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Union

import msgpack
import numpy as np

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

PROTOCOL_VERSION: int = 1
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
RIGID_TOLERANCE = 1e-3  # |R^T R - I| and |bottom row - (0, 0, 0, 1)|, elementwise


# --------------------------------------------------------------------------- messages


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


@dataclass
class SessionConfig:
    session: str  # session name, [A-Za-z0-9_.-]{1,64}
    client_name: str = ""
    role: str = "capture"  # "capture" | "display"
    calibration: CameraCalibration | None = None  # required for role capture
    depth_scale: float = 1000.0  # depth units per metre on the wire (TUM: 5000)
    preset: str = "full"
    overrides: dict[str, bool | int | float | str] = field(default_factory=dict)
    virtual_scene: str | None = None
    mode: str = "live"  # "live" | "lossless"
    want_composite: bool = False


@dataclass
class Hello:
    protocol_version: int
    config: SessionConfig


@dataclass
class Welcome:
    protocol_version: int
    session: str
    credits: int  # frames the capture client may send before the next Credit (lossless)
    heartbeat_interval_s: float
    server_name: str = "arlight"


@dataclass
class Frame:
    seq: int  # >= 0, per session, increasing
    timestamp: float  # capture time, sender clock, seconds
    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) uint16, SessionConfig.depth_scale units per metre, 0 = missing
    pose: np.ndarray | None = None  # (4, 4) float64 camera-to-world
    panorama: np.ndarray | None = None  # (h, w, 3) uint8 RGB equirectangular
    color_codec: str = DEFAULT_COLOR_CODEC  # also used for the panorama
    depth_codec: str = DEFAULT_DEPTH_CODEC
    jpeg_quality: int = DEFAULT_JPEG_QUALITY


@dataclass
class Result:
    seq: int
    timestamp: float  # the frame's capture timestamp, sender clock, seconds
    sh: list[float]  # radiance SH, luminance, L^2 coefficients
    sh_rgb: list[list[float]] | None  # 3 x L^2
    dominant_direction_camera: list[float]  # unit vector towards the light
    dominant_direction_world: list[float]
    intensity: float
    confidence: dict
    pose: list[list[float]]  # 4 x 4 camera-to-world
    timings_ms: dict[str, float]
    frames_received: int  # session counters so far
    frames_processed: int
    frames_dropped: int
    server_receive_time: float  # server clock, seconds
    server_finish_time: float
    composite: np.ndarray | None = None  # (H, W, 3) uint8 RGB
    composite_codec: str = "jpeg"
    jpeg_quality: int = DEFAULT_JPEG_QUALITY


@dataclass
class Credit:
    credits: int  # lossless flow control: capture may send this many more frames


@dataclass
class Error:
    code: str
    message: str
    field: str | None = None
    seq: int | None = None


@dataclass
class Heartbeat:
    time: float  # sender clock, seconds


@dataclass
class Bye:
    reason: str = ""


Message = Union[Hello, Welcome, Frame, Result, Credit, Error, Heartbeat, Bye]  # noqa: UP007

MESSAGE_TYPES: dict[str, type] = {
    "hello": Hello,
    "welcome": Welcome,
    "frame": Frame,
    "result": Result,
    "credit": Credit,
    "error": Error,
    "heartbeat": Heartbeat,
    "bye": Bye,
}
_TYPE_NAMES = {cls: name for name, cls in MESSAGE_TYPES.items()}


def error_from_exception(exc: BaseException, seq: int | None = None) -> Error:
    """The Error message to send for an exception (ProtocolError keeps its code and field)."""
    if isinstance(exc, ProtocolError):
        return Error(exc.code, exc.message[:4096], exc.field, seq)
    return Error("internal", f"{type(exc).__name__}: {exc}"[:4096], None, seq)


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
    m = np.array(rows, dtype=np.float64)
    r = m[:3, :3]
    if (
        np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > RIGID_TOLERANCE
        or np.abs(r.T @ r - np.eye(3)).max() > RIGID_TOLERANCE
        or np.linalg.det(r) <= 0
    ):
        raise ProtocolError(
            "bad_field",
            f"not a rigid transform (rotation orthonormal with det +1, last row 0 0 0 1; "
            f"tolerance {RIGID_TOLERANCE})",
            name,
        )
    return m


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


# --------------------------------------------------------------------------- images


_COLOR_KEYS = frozenset(("format", "encoding", "width", "height", "step", "buffer", "quality"))
_DEPTH_KEYS = frozenset(("format", "encoding", "width", "height", "step", "buffer"))


class _Images:
    """Descriptors of a message's images, checked against the parts before decoding."""

    def __init__(self, parts: list[memoryview] | None, max_pixels: int):
        self.parts = parts  # None: validate descriptors only (encode side)
        self.used: set[int] = set()
        self.max_pixels = max_pixels

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
        if d is None or self.parts is None:
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


# --------------------------------------------------------------------------- per type


def _read_calibration(m: _Map) -> CameraCalibration:
    width = m.int("width", 1, MAX_IMAGE_SIDE)
    height = m.int("height", 1, MAX_IMAGE_SIDE)
    k = m.floats("K", 9)
    if k[1] != 0 or k[3] != 0 or k[6] != 0 or k[7] != 0 or k[8] != 1:
        raise ProtocolError(
            "bad_field", "K must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)", m.f("K")
        )
    if not (k[0] > 0 and k[4] > 0):
        raise ProtocolError("bad_field", f"focal lengths must be > 0, got {k[0]}, {k[4]}", m.f("K"))
    model = m.str("distortion_model", 64)
    d = m.floats("D", max_len=16)
    m.done()
    return CameraCalibration(width, height, k[0], k[4], k[2], k[5], model, tuple(d))


def _write_calibration(c: CameraCalibration) -> dict:
    return {
        "width": _to_plain(c.width),
        "height": _to_plain(c.height),
        "K": _to_plain([c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0]),
        "distortion_model": c.distortion_model,
        "D": _to_plain(list(c.D)),
    }


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


def _read_hello(h: _Map, v: int, images: _Images) -> Hello:
    c = h.map("config")
    session = c.str("session", 64, _NAME_RE)
    client_name = c.str("client_name", 128)
    role = c.str("role", choices=ROLES)
    cal = c.map("calibration", nullable=True)
    calibration = None if cal is None else _read_calibration(cal)
    if role == "capture" and calibration is None:
        raise ProtocolError("bad_field", "required for role capture", c.f("calibration"))
    depth_scale = c.float("depth_scale", 1e-6, 1e9)
    if depth_scale <= 0:
        raise ProtocolError("bad_field", "must be > 0", c.f("depth_scale"))
    preset = c.str("preset", 64, _NAME_RE)
    overrides = _read_overrides(c.raw("overrides"), c.f("overrides"))
    virtual_scene = c.str("virtual_scene", 1024, nullable=True)
    mode = c.str("mode", choices=MODES)
    want_composite = c.bool("want_composite")
    c.done()
    config = SessionConfig(
        session,
        client_name,
        role,
        calibration,
        depth_scale,
        preset,
        overrides,
        virtual_scene,
        mode,
        want_composite,
    )
    return Hello(v, config)


def _write_hello(msg: Hello, parts: list) -> dict:
    c = msg.config
    return {
        "config": {
            "session": c.session,
            "client_name": c.client_name,
            "role": c.role,
            "calibration": None if c.calibration is None else _write_calibration(c.calibration),
            "depth_scale": _to_plain(c.depth_scale),
            "preset": c.preset,
            "overrides": _to_plain(c.overrides),
            "virtual_scene": c.virtual_scene,
            "mode": c.mode,
            "want_composite": _to_plain(c.want_composite),
        }
    }


def _read_welcome(h: _Map, v: int, images: _Images) -> Welcome:
    return Welcome(
        v,
        h.str("session", 64, _NAME_RE),
        h.int("credits", 0, MAX_CREDITS),
        h.float("heartbeat_interval_s", 1e-3, 3600.0),
        h.str("server_name", 128),
    )


def _write_welcome(msg: Welcome, parts: list) -> dict:
    return {
        "session": msg.session,
        "credits": _to_plain(msg.credits),
        "heartbeat_interval_s": _to_plain(msg.heartbeat_interval_s),
        "server_name": msg.server_name,
    }


def _read_frame(h: _Map, v: int, images: _Images) -> Frame:
    seq = h.int("seq")
    timestamp = h.float("timestamp")
    pose = h.raw("pose", nullable=True)
    pose = None if pose is None else _pose(pose, h.f("pose"))
    dc = images.descriptor(h, "color", depth=False)
    dd = images.descriptor(h, "depth", depth=True)
    dp = images.descriptor(h, "panorama", depth=False, nullable=True)
    if (dc[2], dc[3]) != (dd[2], dd[3]):
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
    quality = dc[0].get("quality", DEFAULT_JPEG_QUALITY)
    return Frame(seq, timestamp, color, depth, pose, panorama, dc[1], dd[1], quality)


def _write_frame(msg: Frame, parts: list) -> dict:
    nm = "frame"
    color = msg.color
    depth = msg.depth
    if isinstance(color, np.ndarray) and isinstance(depth, np.ndarray):
        if color.shape[:2] != depth.shape[:2]:
            raise ProtocolError(
                "bad_field",
                f"depth shape {depth.shape} and colour shape {color.shape} must agree in (H, W)",
                f"{nm}.depth",
            )
    out: dict[str, Any] = {
        "seq": _to_plain(msg.seq),
        "timestamp": _to_plain(msg.timestamp),
        "pose": None if msg.pose is None else _pose_to_wire(msg.pose, f"{nm}.pose"),
    }
    out["color"] = _add_image(
        parts, *encode_color(color, msg.color_codec, msg.jpeg_quality, field=f"{nm}.color")
    )
    out["depth"] = _add_image(parts, *encode_depth(depth, msg.depth_codec, field=f"{nm}.depth"))
    out["panorama"] = (
        None
        if msg.panorama is None
        else _add_image(
            parts,
            *encode_color(msg.panorama, msg.color_codec, msg.jpeg_quality, field=f"{nm}.panorama"),
        )
    )
    return out


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


def _read_result(h: _Map, v: int, images: _Images) -> Result:
    seq = h.int("seq")
    timestamp = h.float("timestamp")
    sh = h.floats("sh", max_len=1024)
    bands = math.isqrt(len(sh))
    if not sh or bands * bands != len(sh):
        raise ProtocolError("bad_field", f"{len(sh)} coefficients is not L^2 for L >= 1", h.f("sh"))
    sh_rgb = h.raw("sh_rgb", nullable=True)
    if sh_rgb is not None:
        if type(sh_rgb) is not list or len(sh_rgb) != 3:
            raise ProtocolError(
                "bad_field", "expected 3 arrays (R, G, B) of L^2 numbers", h.f("sh_rgb")
            )
        sh_rgb = [_floats(c, f"{h.f('sh_rgb')}[{i}]", len(sh)) for i, c in enumerate(sh_rgb)]
    dir_cam = h.floats("dominant_direction_camera", 3)
    dir_world = h.floats("dominant_direction_world", 3)
    intensity = h.float("intensity")
    confidence = _plain_map(h.raw("confidence"), h.f("confidence"), 0, 64)
    pose = _pose(h.raw("pose"), h.f("pose")).tolist()
    timings = _plain_map(h.raw("timings_ms"), h.f("timings_ms"), 0, 64)
    timings = {k: _float(x, f"{h.f('timings_ms')}.{k}", 0.0) for k, x in timings.items()}
    received = h.int("frames_received")
    processed = h.int("frames_processed")
    dropped = h.int("frames_dropped")
    t_recv = h.float("server_receive_time")
    t_fin = h.float("server_finish_time")
    dc = images.descriptor(h, "composite", depth=False, nullable=True)
    h.done()
    images.done(h.name)
    composite = images.decode(dc)
    codec = "jpeg" if dc is None else dc[1]
    quality = DEFAULT_JPEG_QUALITY if dc is None else dc[0].get("quality", DEFAULT_JPEG_QUALITY)
    return Result(
        seq,
        timestamp,
        sh,
        sh_rgb,
        dir_cam,
        dir_world,
        intensity,
        confidence,
        pose,
        timings,
        received,
        processed,
        dropped,
        t_recv,
        t_fin,
        composite,
        codec,
        quality,
    )


def _write_result(msg: Result, parts: list) -> dict:
    out = {
        "seq": _to_plain(msg.seq),
        "timestamp": _to_plain(msg.timestamp),
        "sh": _float_list(msg.sh, "result.sh"),
        "sh_rgb": None if msg.sh_rgb is None else _float_list(msg.sh_rgb, "result.sh_rgb"),
        "dominant_direction_camera": _float_list(
            msg.dominant_direction_camera, "result.dominant_direction_camera"
        ),
        "dominant_direction_world": _float_list(
            msg.dominant_direction_world, "result.dominant_direction_world"
        ),
        "intensity": _to_plain(msg.intensity),
        "confidence": _to_plain(msg.confidence),
        "pose": _pose_to_wire(msg.pose, "result.pose"),
        "timings_ms": _to_plain(msg.timings_ms),
        "frames_received": _to_plain(msg.frames_received),
        "frames_processed": _to_plain(msg.frames_processed),
        "frames_dropped": _to_plain(msg.frames_dropped),
        "server_receive_time": _to_plain(msg.server_receive_time),
        "server_finish_time": _to_plain(msg.server_finish_time),
        "composite": None,
    }
    if msg.composite is not None:
        out["composite"] = _add_image(
            parts,
            *encode_color(
                msg.composite, msg.composite_codec, msg.jpeg_quality, field="result.composite"
            ),
        )
    return out


def _float_list(v: Any, name: str) -> list:
    try:
        return np.asarray(v, dtype=np.float64).tolist()
    except (TypeError, ValueError):
        raise ProtocolError("bad_field", "expected numbers", name) from None


def _read_credit(h: _Map, v: int, images: _Images) -> Credit:
    return Credit(h.int("credits", 0, MAX_CREDITS))


def _read_error(h: _Map, v: int, images: _Images) -> Error:
    return Error(
        h.str("code", 32, _CODE_RE),
        h.str("message", 4096),
        h.str("field", 256, nullable=True),
        h.int("seq", nullable=True),
    )


def _read_heartbeat(h: _Map, v: int, images: _Images) -> Heartbeat:
    return Heartbeat(h.float("time"))


def _read_bye(h: _Map, v: int, images: _Images) -> Bye:
    return Bye(h.str("reason", 1024))


_READERS = {
    "hello": _read_hello,
    "welcome": _read_welcome,
    "frame": _read_frame,
    "result": _read_result,
    "credit": _read_credit,
    "error": _read_error,
    "heartbeat": _read_heartbeat,
    "bye": _read_bye,
}
_WRITERS = {
    "hello": _write_hello,
    "welcome": _write_welcome,
    "frame": _write_frame,
    "result": _write_result,
    "credit": lambda m, p: {"credits": _to_plain(m.credits)},
    "error": lambda m, p: {
        "code": m.code,
        "message": m.message,
        "field": m.field,
        "seq": _to_plain(m.seq),
    },
    "heartbeat": lambda m, p: {"time": _to_plain(m.time)},
    "bye": lambda m, p: {"reason": m.reason},
}


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
    header.update(_WRITERS[name](msg, parts))
    if parts:
        header["buffers"] = [len(as_bytes_view(p)) for p in parts]
    if version != PROTOCOL_VERSION:  # a deliberately wrong version (tests); skip the checks
        return [msgpack.packb(header, use_bin_type=True), *parts]
    m = _Map(header, name)
    m.seen.update(("v", "type", "buffers"))
    _READERS[name](m, version, _Images(None, max_pixels))
    m.done()
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
    msg = _READERS[name](m, header["v"], images)
    m.done()
    images.done(name)
    return msg
