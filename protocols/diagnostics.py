"""Result.diagnostics as the wire carries it (SPEC.md section 4, "diagnostics"): plain values
only, bounded in depth, entries, array length, string length and values in all."""

from __future__ import annotations

from typing import Any, cast

from arlight.core.contracts import Diagnostics

from .errors import ProtocolError
from .fields import KEY_RE, read_str, to_plain, type_name

# Result.diagnostics (SPEC.md section 4, "diagnostics"): plain values only, bounded.
DIAGNOSTICS_MAX_DEPTH = 4  # levels of maps, the diagnostics map itself being level 1
DIAGNOSTICS_MAX_KEYS = 64  # entries per map
DIAGNOSTICS_MAX_ARRAY = 1024  # numbers per array
DIAGNOSTICS_MAX_STR = 1024  # characters per string
DIAGNOSTICS_MAX_VALUES = 4096  # scalars plus array elements, in all
_DIAGNOSTIC_TYPES = "nil, bool, int, float, str, arrays of numbers and maps of these"


def plain_diagnostics(diagnostics: Any, name: str = "result.diagnostics") -> Diagnostics:
    """Result.diagnostics as the wire carries it: numpy values and tuples made plain, then
    checked against the limits; ProtocolError (bad_field, naming the key) for anything else."""
    return read_diagnostics(to_plain(diagnostics), name)


def read_diagnostics(v: Any, name: str) -> Diagnostics:
    """Check a diagnostics map (decode, and encode before sending); arrays become floats.
    The keys are whatever came (a client must not fail on keys it does not know), typed as
    the ones arlight sends (arlight.core.contracts.Diagnostics)."""
    budget = [DIAGNOSTICS_MAX_VALUES]
    return cast(Diagnostics, _diagnostics_map(v, name, 1, budget))


def _diagnostics_map(v: Any, name: str, level: int, budget: list[int]) -> dict:
    if type(v) is not dict:
        raise ProtocolError("bad_field", f"expected a map, got {type_name(v)}", name)
    if len(v) > DIAGNOSTICS_MAX_KEYS:
        raise ProtocolError("bad_field", f"{len(v)} entries, at most {DIAGNOSTICS_MAX_KEYS}", name)
    out = {}
    for k, x in v.items():
        key = read_str(k, f"{name} key", 64, KEY_RE)
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
            raise ProtocolError("bad_field", f"{n} numbers, at most {DIAGNOSTICS_MAX_ARRAY}", name)
        out = []
        for i, e in enumerate(x):
            if type(e) not in (int, float):
                raise ProtocolError(
                    "bad_field", f"arrays hold numbers only, got {type_name(e)}", f"{name}[{i}]"
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
        "bad_field",
        f"unsupported value type {t.__name__}; diagnostics hold {_DIAGNOSTIC_TYPES}",
        name,
    )
