"""Engine layouts (SPEC.md section 4, "engine layouts"): the names a capture Hello may ask
for (SessionConfig.exports) and the numbers each Result then carries (Result.exports)."""

from __future__ import annotations

from typing import Any

from .errors import ProtocolError
from .fields import read_float, read_float_rows, read_floats, read_str, type_name

# The names of arlight.pipeline.engine_export.EXPORTERS (the protocol does not import the
# pipeline; tests/test_protocols_fields.py checks the two lists agree).
EXPORT_LAYOUTS = ("arcore", "webxr", "gltf", "unity", "filament", "main_light")
MAX_FILAMENT_TEXT = 2**17  # characters: 1024 coefficients (Result.sh's limit) of ~70 each


def read_export_names(v: Any, name: str) -> tuple[str, ...]:
    """Hello.config.exports: 1..6 distinct layout names, or nil (= none); an empty array is
    refused (SPEC.md section 4: none is nil or the key absent)."""
    if v is None:
        return ()
    if v == []:
        raise ProtocolError(
            "bad_field", "an empty array: for no layout send nil or omit the key", name
        )
    if type(v) is not list or not 1 <= len(v) <= len(EXPORT_LAYOUTS):
        raise ProtocolError(
            "bad_field",
            f"expected an array of 1..{len(EXPORT_LAYOUTS)} layout names, got {type_name(v)}",
            name,
        )
    names = tuple(read_str(x, f"{name}[{i}]", 64, choices=EXPORT_LAYOUTS) for i, x in enumerate(v))
    if len(set(names)) != len(names):
        raise ProtocolError("bad_field", f"a layout named twice: {list(names)}", name)
    return names


def _read_layout(layout: str, v: Any, name: str) -> Any:
    """One engine layout's numbers, checked for shape and finiteness (SPEC.md table)."""
    if layout in ("arcore", "webxr"):
        return read_floats(v, name, 27)
    if layout == "unity":
        return read_float_rows(v, name, 3, 9)
    if layout == "filament":
        return read_str(v, name, MAX_FILAMENT_TEXT)
    keys = {
        "gltf": ("intensity", "rotation", "irradianceCoefficients"),
        "main_light": ("direction", "intensity"),
    }[layout]
    if type(v) is not dict or set(v) != set(keys):
        raise ProtocolError(
            "bad_field",
            f"expected a map with keys {', '.join(keys)}, got "
            f"{sorted(map(str, v)) if type(v) is dict else type_name(v)}",
            name,
        )
    if layout == "main_light":
        return {k: read_floats(v[k], f"{name}.{k}", 3) for k in keys}
    return {
        "intensity": read_float(v["intensity"], f"{name}.intensity"),
        "rotation": read_floats(v["rotation"], f"{name}.rotation", 4),
        "irradianceCoefficients": read_float_rows(
            v["irradianceCoefficients"], f"{name}.irradianceCoefficients", 9, 3
        ),
    }


def read_exports(v: Any, name: str) -> dict:
    """Result.exports: layout name -> that layout's numbers (each layout at most once)."""
    if type(v) is not dict or not 1 <= len(v) <= len(EXPORT_LAYOUTS):
        raise ProtocolError(
            "bad_field",
            f"expected a map of 1..{len(EXPORT_LAYOUTS)} layouts, got {type_name(v)}",
            name,
        )
    out = {}
    for k, x in v.items():
        layout = read_str(k, f"{name} key", 64, choices=EXPORT_LAYOUTS)
        out[layout] = _read_layout(layout, x, f"{name}.{layout}")
    return out
