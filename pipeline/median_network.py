"""Lower medians of small pixel windows, a row of pixels at a time, by a selection network.

The depth filter's D'' and D''' (:mod:`arlight.pipeline.depth_filter`) take, at each pixel,
the lower median (rank ``(n - 1) // 2``) of the n valid samples among m candidates (D'':
the 5x5 sub-sampled window, m = 25, gated by intensity; D''': m = 4). Per pixel that is
O(m^2) rank counting. Here a row's m candidates are gathered into an (m, W) buffer and a
fixed selection network runs across the row: each comparator is a min / max over W pixels
at once, which LLVM vectorises.

A network needs m values at every pixel, so a missing or gated-out candidate becomes -inf
or +inf. A pixel's missing candidates alternate, -inf first for odd m and +inf first for
even m; that makes ``(m - 1) // 2 - (n - 1) // 2`` of them -inf and the rest +inf, so the
network's middle output (rank ``(m - 1) // 2``) is the valid samples' rank ``(n - 1) // 2``
(and -inf, reported as 0, when n = 0). The network is Batcher's odd-even merge sort for the
next power of two, its comparators beyond m dropped (+inf there never moves) and those
that cannot reach the middle output pruned (m = 25: 113 comparators). A network only
moves samples, so the result is the per-pixel kernel's bit for bit (tested); depth must be
finite (the filter's checks).
"""

from __future__ import annotations

import functools

import numba
import numpy as np
from numba import prange

__all__ = ["MAX_NETWORK_INPUTS", "median_network", "support_median_rows"]

MAX_NETWORK_INPUTS = 32  # larger windows keep the per-pixel selection (not measured there)


def _odd_even_merge(lo: int, n: int, r: int) -> list[tuple[int, int]]:
    """Comparators merging the two sorted halves of [lo, lo + n) taken with stride r."""
    step = 2 * r
    if step >= n:
        return [(lo, lo + r)]
    pairs = _odd_even_merge(lo, n, step) + _odd_even_merge(lo + r, n, step)
    pairs += [(i, i + r) for i in range(lo + r, lo + n - r, step)]
    return pairs


def _odd_even_sort(lo: int, n: int) -> list[tuple[int, int]]:
    """Batcher's odd-even merge sort of [lo, lo + n), n a power of two."""
    if n < 2:
        return []
    half = n // 2
    return _odd_even_sort(lo, half) + _odd_even_sort(lo + half, half) + _odd_even_merge(lo, n, 1)


@functools.cache
def median_network(m: int) -> np.ndarray:
    """(C, 2) int64 comparators (i < j: position i gets the min, j the max) after which
    position (m - 1) // 2 of m inputs holds the input of that rank. 1 <= m <= 32."""
    if not 1 <= m <= MAX_NETWORK_INPUTS:
        raise ValueError(f"a median network takes 1..{MAX_NETWORK_INPUTS} inputs, got {m}")
    size = 1
    while size < m:
        size *= 2
    pairs = [(i, j) for i, j in _odd_even_sort(0, size) if j < m]
    needed = {(m - 1) // 2}
    kept: list[tuple[int, int]] = []
    for i, j in reversed(pairs):
        if i in needed or j in needed:
            kept.append((i, j))
            needed.update((i, j))
    return np.array(kept[::-1], dtype=np.int64).reshape(-1, 2)


@numba.njit(parallel=True, cache=True)
def support_median_rows(depth, intensity, offsets, lam_i, network, out):
    """out[y, x] = lower median of depth[y + oy, x + ox] > 0 (oy, ox in offsets) with
    |I(y, x) - I(q)| < lam_i (inf: no gate); 0 where none is valid. depth: (H, W) float32
    finite metres; intensity finite; network: :func:`median_network` of len(offsets)**2."""
    h, w = out.shape
    k = offsets.shape[0]
    m = k * k
    for row in prange(h):
        y = np.int64(row)  # prange may type its index unsigned; int64 keeps the index maths
        buf = np.empty((m, w), np.float32)
        # missing candidates alternate -inf, +inf (odd m: -inf first; even m: +inf first),
        # which leaves the valid samples' lower median in the middle output; sign holds
        # each pixel's next fill (-1 or +1)
        sign = np.full(w, np.float32(-1.0 if m % 2 == 1 else 1.0))
        t = 0
        for a in range(k):
            qy = y + offsets[a]
            for b in range(k):
                line = buf[t]
                t += 1
                ox = offsets[b]
                x0 = max(0, -ox)
                x1 = min(w, w - ox)
                if qy < 0 or qy >= h:
                    x0 = x1 = 0
                _fill_missing(line[:x0], sign[:x0])
                _fill_missing(line[x1:], sign[x1:])
                if x1 > x0:
                    _gather(
                        line[x0:x1],
                        sign[x0:x1],
                        depth[qy, x0 + ox : x1 + ox],
                        intensity[qy, x0 + ox : x1 + ox],
                        intensity[y, x0:x1],
                        lam_i,
                    )
        for c in range(network.shape[0]):
            _compare_exchange(buf[network[c, 0]], buf[network[c, 1]])
        result = buf[(m - 1) // 2]
        for x in range(w):
            v = result[x]
            out[y, x] = v if v > -np.inf else np.float32(0.0)  # -inf: no valid sample


@numba.njit(inline="always")
def _gather(line, sign, depth, intensity, centre, lam_i):
    """One candidate across a row: its depth where valid, else the pixel's next fill."""
    for i in range(line.shape[0]):
        dq = depth[i]
        ok = (dq > 0) & (abs(centre[i] - intensity[i]) < lam_i)
        s = sign[i]
        line[i] = dq if ok else s * np.float32(np.inf)
        sign[i] = s if ok else -s


@numba.njit(inline="always")
def _fill_missing(line, sign):
    for i in range(line.shape[0]):
        s = sign[i]
        line[i] = s * np.float32(np.inf)
        sign[i] = -s


@numba.njit(inline="always")
def _compare_exchange(first, second):
    """first, second = min, max element-wise (selects, not min / max: LLVM vectorises them)."""
    for x in range(first.shape[0]):
        u = first[x]
        v = second[x]
        first[x] = u if u < v else v
        second[x] = u if u >= v else v
