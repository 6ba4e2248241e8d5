"""The protocol's numbers and its schema reader (SPEC.md sections 2 and 4).

The version, the limits on what crosses the wire, the name and token patterns; `FieldReader`,
a header map read with typed getters that name the offending field; the scalar, array, pose
and plain-map readers every message uses; `to_plain` and the encode-side helpers that turn
numpy values into what msgpack packs. Any value that breaks a rule raises ProtocolError
(``bad_field``) naming the field.
"""

from __future__ import annotations

import builtins
import math
import re
import secrets
from enum import Enum
from typing import Any, Literal, overload

import numpy as np

from arlight.core.checks import RIGID_TOLERANCE, CheckError, check_rigid

from .errors import ProtocolError

PROTOCOL_VERSION: int = 2  # 2: Error.retryable, Bye.kind, Result.sh_camera/diagnostics
DEFAULT_MAX_MESSAGE_BYTES: int = 64 * 2**20  # whole multipart message
MAX_HEADER_BYTES: int = 2**20  # the msgpack header part
MAX_PARTS: int = 16  # header + buffers

ROLES = ("capture", "display")
MODES = ("live", "lossless")
MAX_INT = 2**63 - 1
MAX_CREDITS = 2**20
NAME_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
KEY_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
CODE_RE = re.compile(r"[a-z0-9_]{1,32}")
# a session token or the server's admin token (SPEC.md section 4, "session tokens"): the
# alphabet of secrets.token_urlsafe, 16..128 characters (at least 96 bits when random)
TOKEN_RE = re.compile(r"[A-Za-z0-9_\-]{16,128}")
TOKEN_BYTES = 24  # random bytes of a generated token: 32 characters of token_urlsafe


def new_token() -> str:
    """A random session or admin token (192 bits, URL-safe, matching TOKEN_RE)."""
    return secrets.token_urlsafe(TOKEN_BYTES)


# --------------------------------------------------------------------------- field checks


class FieldReader:
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

    # the getters are named after the types they read: inside the class, the annotations
    # name the types as builtins.int, builtins.str, ...
    @overload
    def int(
        self,
        key: builtins.str,
        lo: builtins.int = 0,
        hi: builtins.int = MAX_INT,
        nullable: Literal[False] = False,
    ) -> builtins.int: ...

    @overload
    def int(
        self,
        key: builtins.str,
        lo: builtins.int = 0,
        hi: builtins.int = MAX_INT,
        *,
        nullable: builtins.bool,
    ) -> builtins.int | None: ...

    def int(
        self,
        key: builtins.str,
        lo: builtins.int = 0,
        hi: builtins.int = MAX_INT,
        nullable: builtins.bool = False,
    ) -> builtins.int | None:
        v = self.raw(key, nullable)
        if v is None:
            return None
        if type(v) is not int:
            raise ProtocolError(
                "bad_field", f"expected an integer, got {type_name(v)}", self.f(key)
            )
        if not lo <= v <= hi:
            raise ProtocolError("bad_field", f"{v} is outside {lo}..{hi}", self.f(key))
        return v

    def float(
        self, key: builtins.str, lo: builtins.float = -math.inf, hi: builtins.float = math.inf
    ) -> builtins.float:
        return read_float(self.raw(key), self.f(key), lo, hi)

    def bool(self, key: builtins.str) -> builtins.bool:
        v = self.raw(key)
        if type(v) is not bool:
            raise ProtocolError("bad_field", f"expected a boolean, got {type_name(v)}", self.f(key))
        return v

    @overload
    def str(
        self,
        key: builtins.str,
        max_len: builtins.int = 1024,
        pattern: re.Pattern | None = None,
        choices: tuple | None = None,
        nullable: Literal[False] = False,
    ) -> builtins.str: ...

    @overload
    def str(
        self,
        key: builtins.str,
        max_len: builtins.int = 1024,
        pattern: re.Pattern | None = None,
        choices: tuple | None = None,
        *,
        nullable: builtins.bool,
    ) -> builtins.str | None: ...

    def str(
        self,
        key: builtins.str,
        max_len: builtins.int = 1024,
        pattern: re.Pattern | None = None,
        choices: tuple | None = None,
        nullable: builtins.bool = False,
    ) -> builtins.str | None:
        v = self.raw(key, nullable)
        if v is None:
            return None
        return read_str(v, self.f(key), max_len, pattern, choices)

    def floats(
        self, key: builtins.str, n: builtins.int | None = None, max_len: builtins.int = 1024
    ) -> list[builtins.float]:
        return read_floats(self.raw(key), self.f(key), n, max_len)

    @overload
    def map(self, key: builtins.str, nullable: Literal[False] = False) -> FieldReader: ...

    @overload
    def map(self, key: builtins.str, nullable: builtins.bool) -> FieldReader | None: ...

    def map(self, key: builtins.str, nullable: builtins.bool = False) -> FieldReader | None:
        v = self.raw(key, nullable)
        return None if v is None else FieldReader(v, self.f(key))

    def done(self) -> None:
        extra = [k for k in self.d if k not in self.seen]
        if extra:
            k = extra[0]
            shown = k if isinstance(k, str) else repr(k)
            raise ProtocolError(
                "bad_field", f"unknown field {str(shown)[:64]!r}", f"{self.name}.{str(shown)[:64]}"
            )


def type_name(v: Any) -> str:
    return "nil" if v is None else type(v).__name__


def read_float(v: Any, name: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if type(v) not in (int, float):
        raise ProtocolError("bad_field", f"expected a number, got {type_name(v)}", name)
    v = float(v)
    if not math.isfinite(v):
        raise ProtocolError("bad_field", f"{v} is not finite", name)
    if not lo <= v <= hi:
        raise ProtocolError("bad_field", f"{v} is outside {lo}..{hi}", name)
    return v


def read_str(
    v: Any,
    name: str,
    max_len: int = 1024,
    pattern: re.Pattern | None = None,
    choices: tuple | None = None,
) -> str:
    if type(v) is not str:
        raise ProtocolError("bad_field", f"expected a string, got {type_name(v)}", name)
    if len(v) > max_len:
        raise ProtocolError("bad_field", f"{len(v)} characters, at most {max_len}", name)
    if choices is not None and v not in choices:
        raise ProtocolError("bad_field", f"{v[:64]!r} is not one of {choices}", name)
    if pattern is not None and not pattern.fullmatch(v):
        raise ProtocolError("bad_field", f"{v[:64]!r} does not match {pattern.pattern}", name)
    return v


def read_token(v: Any, name: str) -> str:
    """A token (TOKEN_RE); the message never repeats the value (it may be a near-secret)."""
    if type(v) is not str or not TOKEN_RE.fullmatch(v):
        size = f" of {len(v)} characters" if type(v) is str else ""
        raise ProtocolError(
            "bad_field",
            f"not a token: expected 16..128 characters from "
            f"A-Z a-z 0-9 _ -, got a {type_name(v)}{size}",
            name,
        )
    return v


def read_floats(v: Any, name: str, n: int | None = None, max_len: int = 1024) -> list[float]:
    if type(v) is not list:
        raise ProtocolError("bad_field", f"expected an array of numbers, got {type_name(v)}", name)
    if n is not None and len(v) != n:
        raise ProtocolError("bad_field", f"{len(v)} numbers, expected {n}", name)
    if len(v) > max_len:
        raise ProtocolError("bad_field", f"{len(v)} numbers, at most {max_len}", name)
    return [read_float(x, f"{name}[{i}]") for i, x in enumerate(v)]


def read_pose(v: Any, name: str) -> np.ndarray:
    """4 x 4 finite rigid camera-to-world matrix, rows as arrays."""
    if type(v) is not list or len(v) != 4:
        raise ProtocolError("bad_field", "expected 4 rows of 4 numbers (a 4 x 4 matrix)", name)
    rows = [read_floats(r, f"{name}[{i}]", 4) for i, r in enumerate(v)]
    try:
        return check_rigid(rows, name, RIGID_TOLERANCE)  # the one rule (arlight.core.checks)
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
        return read_plain_map(v, name, depth + 1)
    raise ProtocolError("bad_field", f"unsupported value type {type_name(v)}", name)


def read_plain_map(v: Any, name: str, depth: int = 0, max_items: int = 256) -> dict:
    if type(v) is not dict:
        raise ProtocolError("bad_field", f"expected a map, got {type_name(v)}", name)
    if len(v) > max_items:
        raise ProtocolError("bad_field", f"{len(v)} entries, at most {max_items}", name)
    out = {}
    for k, x in v.items():
        key = read_str(k, f"{name} key", 64, KEY_RE)
        out[key] = _plain_value(x, f"{name}.{key}", depth)
    return out


def to_plain(v: Any) -> Any:
    """numpy scalars/arrays and tuples -> Python values msgpack packs (encode side)."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [to_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: to_plain(x) for k, x in v.items()}
    return v


def pose_to_wire(pose: Any, name: str) -> list:
    try:
        m = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise ProtocolError("bad_field", "expected a 4 x 4 matrix of numbers", name) from None
    if m.shape != (4, 4):
        raise ProtocolError("bad_field", f"expected shape (4, 4), got {m.shape}", name)
    return m.tolist()


def float_list(v: Any, name: str) -> list:
    try:
        return np.asarray(v, dtype=np.float64).tolist()
    except (TypeError, ValueError):
        raise ProtocolError("bad_field", "expected numbers", name) from None


def read_float_rows(v: Any, name: str, rows: int, cols: int) -> list[list[float]]:
    if type(v) is not list or len(v) != rows:
        raise ProtocolError(
            "bad_field", f"expected {rows} arrays of {cols} numbers, got {type_name(v)}", name
        )
    return [read_floats(r, f"{name}[{i}]", cols) for i, r in enumerate(v)]


class WireEnum(str, Enum):
    """An Enum of wire strings: members equal, print and format as their value."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)
