"""Reductions over a short last axis (RGB channels, xyz components), one ufunc per channel.

NumPy reduces along a last axis of length 3 element by element: `rgb.max(axis=-1)` over a
640x480 image takes 12 ms on this project's 2-core machines, the same per channel 0.5 ms
(docs/results/speed.md, "Reductions per channel"). Results are identical (NaN included).
"""

from __future__ import annotations

import numpy as np


def channel_max(values: np.ndarray) -> np.ndarray:
    """Largest of the last axis' entries (..., C) -> (...), NaN where any entry is NaN."""
    v = np.asarray(values)
    out = v[..., 0].copy()
    for c in range(1, v.shape[-1]):
        np.maximum(out, v[..., c], out=out)
    return out


def any_nonzero(values: np.ndarray) -> np.ndarray:
    """(..., C) -> (...) bool: some entry of the last axis is not zero (NaN counts as one);
    for normal images, where a pixel has a normal."""
    v = np.asarray(values)
    out = v[..., 0] != 0
    for c in range(1, v.shape[-1]):
        out |= v[..., c] != 0
    return out


def vector_length(values: np.ndarray) -> np.ndarray:
    """Euclidean length of the last axis (..., C) -> (...), in the input's precision."""
    v = np.asarray(values)
    out = v[..., 0] * v[..., 0]
    for c in range(1, v.shape[-1]):
        out += v[..., c] * v[..., c]
    return np.sqrt(out)
