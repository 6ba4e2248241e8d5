"""Linear light -> 8-bit sRGB codes (IEC 61966-2-1), the composites' and renders' last step.

The code of a linear value c is ``round(255 * srgb(c))``, c clipped to [0, 1], NaN -> 0
(:func:`_srgb_code`, the definition). Evaluating it needs a power per channel, which took
most of an encoding. The codes are a step function of c: ``THRESHOLDS[k - 1]`` is the
smallest float64 whose code is at least k, found by bisection over the float64 values with
:func:`_srgb_code` itself. A value's code is then the code at the start of its bin of [0, 1)
(4096 bins, a table), plus one where it has reached that code's next step: a comparison
instead of a power, 8x faster, and the definition's code for every float64 (tested on both
sides of every step and of every bin, and on random values).
"""

from __future__ import annotations

import numba
import numpy as np
from numba.extending import register_jitable

__all__ = [
    "TABLE_BASE",
    "TABLE_NEXT",
    "THRESHOLDS",
    "counted_code",
    "encode_scaled_where",
    "encode_where",
    "linear_to_srgb_u8",
]


@register_jitable
def _srgb_code(c):
    """The 8-bit sRGB code of a linear value (clipped to [0, 1]; NaN -> 0): the definition."""
    if not c > 0.0:  # NaN included
        c = 0.0
    elif c > 1.0:
        c = 1.0
    s = 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055
    return np.uint8(s * 255.0 + 0.5)


@numba.njit(cache=True)
def _thresholds() -> np.ndarray:
    """(255,) float64: entry k - 1 is the smallest positive float64 whose code is >= k
    (bisection over the bit patterns, which order positive doubles as integers)."""
    out = np.empty(255, np.float64)
    bits = np.empty(1, np.int64)
    as_float = bits.view(np.float64)
    as_float[0] = 1.0
    one = bits[0]
    for k in range(1, 256):
        lo = np.int64(0)  # code(0.0) = 0 < k
        hi = one  # code(1.0) = 255 >= k
        while hi - lo > 1:
            mid = lo + (hi - lo) // 2
            bits[0] = mid
            if _srgb_code(as_float[0]) >= k:
                hi = mid
            else:
                lo = mid
        bits[0] = hi
        out[k - 1] = as_float[0]
    return out


THRESHOLDS = _thresholds()
_BINS = 4096  # bins of [0, 1) narrow enough that a code changes at most once in one (tested)
TABLE_BASE = np.array([_srgb_code(b / _BINS) for b in range(_BINS)], np.int64)
TABLE_NEXT = np.append(THRESHOLDS, np.inf)  # 256: the next step of any code (none for 255)


@register_jitable(inline="always")
def counted_code(c, base, next_step):
    """`_srgb_code(c)`: the code at the start of c's bin, plus one where c has reached the
    next step (a comparison, not a power; NaN -> 0)."""
    if not c > 0.0:
        return np.uint8(0)
    if c >= 1.0:
        return np.uint8(255)
    code = base[int(c * _BINS)]
    return np.uint8(code + (c >= next_step[code]))


@numba.njit(parallel=True, cache=True)
def _srgb_u8(linear, base, next_step, out):
    for i in numba.prange(linear.shape[0]):
        out[i] = counted_code(linear[i], base, next_step)


@numba.njit(parallel=True, cache=True)
def _encode_where(linear, where, base, next_step, image):
    for y in numba.prange(where.shape[0]):
        for x in range(where.shape[1]):
            if where[y, x]:
                for c in range(image.shape[2]):
                    image[y, x, c] = counted_code(linear[y, x, c], base, next_step)


@numba.njit(parallel=True, cache=True)
def _encode_scaled_where(linear, ratio, delta, where, base, next_step, image):
    for y in numba.prange(where.shape[0]):
        for x in range(where.shape[1]):
            if where[y, x]:
                for c in range(image.shape[2]):
                    value = np.float64(linear[y, x, c]) * ratio[y, x] + delta[y, x, c]
                    image[y, x, c] = counted_code(value, base, next_step)


def linear_to_srgb_u8(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> 8-bit sRGB (IEC 61966-2-1), clipped, rounded to nearest; NaN -> 0.
    Computed in float64 whatever the input's precision."""
    c = np.ascontiguousarray(linear, np.float64)
    out = np.empty(c.shape, np.uint8)
    _srgb_u8(c.reshape(-1), TABLE_BASE, TABLE_NEXT, out.reshape(-1))
    return out


def encode_where(linear: np.ndarray, where: np.ndarray, image: np.ndarray) -> None:
    """image[where] = linear_to_srgb_u8(linear[where]), in place, without gathering the
    pixels first. linear (H, W, C) float64, where (H, W) bool, image (H, W, C) uint8 (a
    view is fine: the rect of a composite)."""
    linear = np.ascontiguousarray(linear, np.float64)
    _encode_where(linear, where, TABLE_BASE, TABLE_NEXT, image)


def encode_scaled_where(
    linear: np.ndarray, ratio: np.ndarray, delta: np.ndarray, where: np.ndarray, image: np.ndarray
) -> None:
    """image[where] = linear_to_srgb_u8(linear * ratio[..., None] + delta)[where], in place,
    the sum made only where it is encoded (in float64, as numpy would). linear (H, W, C)
    float32 or float64, ratio (H, W) and delta (H, W, C) float64, where (H, W) bool, image
    (H, W, C) uint8 (a view is fine)."""
    _encode_scaled_where(
        np.ascontiguousarray(linear),
        np.ascontiguousarray(ratio, np.float64),
        np.ascontiguousarray(delta, np.float64),
        where,
        TABLE_BASE,
        TABLE_NEXT,
        image,
    )
