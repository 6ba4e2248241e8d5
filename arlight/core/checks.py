"""The checks made where data enters arlight: wire decode, `Pipeline.process`, the readers.

One set of rules for one frame, in the spirit of Kornia's ``KORNIA_CHECK_SHAPE``: every check
raises `CheckError` naming the field, what was expected and what came. Edges translate it into
their own error type (the protocol's ``bad_field``, a data set error naming the file). Inner
stages of the pipeline trust what passed here; public functions that users may call on
their own (the depth filters, `VolumeReconstruction.process`) check their arguments with the
same helpers. Never ``assert`` for input.

Imports numpy only, so that every package (protocols, pipeline, sources) may use it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

RIGID_TOLERANCE = 1e-3  # |R^T R - I| and |last row - (0, 0, 0, 1)|, elementwise
MAX_DEPTH_M = 100.0  # larger (finite) depth values are treated as invalid sensor output


class CheckError(ValueError):
    """A value that breaks a documented limit.

    field: the name the user knows it by ("depth", "frame.pose", a file path);
    message: what was expected and what came.
    """

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

    def __reduce__(self):  # picklable with its fields (multiprocessing, logging handlers)
        return (type(self), (self.field, self.message))


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def check_image(
    array: Any,
    field: str,
    *,
    channels: int | None = None,
    dtype: Any = None,
    size: tuple[int, int] | None = None,
    size_of: str = "the expected",
) -> np.ndarray:
    """`array` as an (H, W) image (channels None) or (H, W, channels) image.

    dtype: required dtype (None: any); size: required (width, height) in pixels, named
    `size_of` in the message ("the camera calibration's"). Returns the array (not copied).
    """
    a = np.asarray(array)
    if channels is None:
        if a.ndim != 2:
            raise CheckError(field, f"expected shape (H, W), got {_shape_text(a.shape)}")
    elif a.ndim != 3 or a.shape[2] != channels:
        raise CheckError(field, f"expected shape (H, W, {channels}), got {_shape_text(a.shape)}")
    if dtype is not None and a.dtype != np.dtype(dtype):
        raise CheckError(field, f"expected dtype {np.dtype(dtype)}, got {a.dtype}")
    if size is not None and (a.shape[1], a.shape[0]) != tuple(size):
        raise CheckError(
            field, f"size {a.shape[1]}x{a.shape[0]} does not match {size_of} {size[0]}x{size[1]}"
        )
    return a


def check_rigid(matrix: Any, field: str, tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """A finite 4x4 rigid transform (rotation orthonormal with det +1, last row 0 0 0 1).

    Elementwise within `tolerance`. Returns it as float64 (a copy).
    """
    try:
        m = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise CheckError(field, "expected a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise CheckError(field, f"expected shape (4, 4), got {_shape_text(m.shape)}")
    if not np.all(np.isfinite(m)):
        raise CheckError(field, "must be finite (NaN or inf found)")
    r = m[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf, refused below
        deviation = float(np.abs(r.T @ r - np.eye(3)).max())
    if (
        np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > tolerance
        or not deviation <= tolerance
        or np.linalg.det(r) <= 0
    ):
        raise CheckError(
            field,
            "not a rigid transform (rotation orthonormal with det +1, "
            f"last row 0 0 0 1; tolerance {tolerance:g})",
        )
    return m


def check_finite(
    value: Any,
    field: str,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
) -> float:
    """A finite real number in [low, high] (low excluded when low_open)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CheckError(field, f"expected a number, got {type(value).__name__}") from None
    if not math.isfinite(v):
        raise CheckError(field, f"must be finite, got {v}")
    if v < low or v > high or (low_open and v == low):
        lo = "(" if low_open else "["
        raise CheckError(field, f"must be in {lo}{low:g}, {high:g}], got {v:g}")
    return v


def depth_metres(depth: Any, depth_scale: float | None, field: str = "depth") -> np.ndarray:
    """(H, W) float32 metres, 0 = missing, from raw sensor depth or from metres.

    depth: (H, W) uint16 sensor units with `depth_scale` units per metre (TUM 5000, mm 1000),
    or floating-point metres with depth_scale None. NaN, inf, negative and > MAX_DEPTH_M -> 0.
    The division is float32 / float32, the same arithmetic everywhere, so recorded integers
    give the same metres on every path (reader, wire, recording). Always a new array.
    """
    d = check_image(depth, field)
    if depth_scale is not None:
        scale = check_finite(depth_scale, f"{field}_scale", low=0.0, low_open=True)
        if d.dtype != np.uint16:
            raise CheckError(
                field,
                f"with a depth_scale, expected uint16 sensor units, got "
                f"dtype {d.dtype} (float depth is metres: no depth_scale)",
            )
        metres = d.astype(np.float32) / np.float32(scale)
    else:
        if not np.issubdtype(d.dtype, np.floating):
            raise CheckError(
                field,
                f"expected float metres, or uint16 with a depth_scale "
                f"(units per metre), got dtype {d.dtype}",
            )
        metres = d.astype(np.float32, copy=True)
    metres[~np.isfinite(metres) | (metres < 0) | (metres > MAX_DEPTH_M)] = 0.0
    return metres
