"""Glossy reflection through prefiltered maps: the glossy lobe evaluated once per texel of a
small equirectangular map per frame and exponent, then one bilinear lookup per pixel
(split-sum style, as a GPU renderer prefilters its environment per roughness).

Frame and mapping: ``pipeline/equirect.py`` (+y up, u = atan2(x, -z) / 2 pi, v = acos(y) /
pi). The lobe and its 36-sample pattern are ``pipeline/glossy.py``'s, with one difference:
the pattern's frame (t, b) about the mirror direction r is always t = normalize(y x r),
b = r x t (``glossy`` turns to the x axis where |r.y| >= 0.9). That frame turns with r about
+y, so all texels of one row of the prefiltered map see the same 36 samples shifted in u by
the texel's column: a row needs the samples' (u, v), weights and mip levels once, and a
texel only the trilinear lookups (no trigonometry per sample).

The prefiltered map of exponent n (:func:`prefilter_height`) is the coarsest pyramid level
whose row angle pi / H is at most theta_r / ``TEXELS_PER_RADIUS`` (theta_r the lobe radius,
``glossy.lobe_radius_rad``): its width divides the finer levels' widths. The glossy value at
a mirror direction is then the bilinear lookup of that map (u wrapped, rows clamped at the
poles). :func:`worth_prefiltering` keeps the per-pixel kernel where the map would cost more
than the pixels it serves (small lobes on few pixels).
"""

from __future__ import annotations

import math
import time

import numba
import numpy as np
from numba.extending import register_jitable

from arlight.pipeline import glossy
from arlight.pipeline.glossy import _RING_COS, _RING_SIN, _bilinear, _uv

# the map's row angle at most theta_r / 3 (PSNR >= 54 dB against the per-pixel lobe at
# roughness 0.05-0.5): docs/results/ibl.md, "The 360 path at video rate"
TEXELS_PER_RADIUS = 3.0
# a texel's 36 lookups (row by row, no trigonometry) cost about this fraction of a pixel's
# (0.38 against 3.4 us, with margin; docs/results/ibl.md, "The 360 path at video rate")
TEXEL_COST = 0.15


def prefilter_height(pyramid: glossy.MipPyramid, exponent: float) -> int:
    """Rows of the prefiltered map of Phong `exponent`: the smallest pyramid level height H
    with pi / H <= theta_r / TEXELS_PER_RADIUS (the map's own height when none is finer)."""
    theta_r = glossy.lobe_radius_rad(exponent)
    need = math.pi * TEXELS_PER_RADIUS / theta_r
    fine = [int(h) for h in pyramid.heights if h >= need]
    return min(fine) if fine else int(pyramid.heights[0])


def worth_prefiltering(pyramid: glossy.MipPyramid, exponent: float, pixels: int) -> bool:
    """True where the prefiltered map of `exponent` costs less than `pixels` per-pixel lobes."""
    h = prefilter_height(pyramid, exponent)
    return 2 * h * h * TEXEL_COST < pixels


@register_jitable
def _row_samples(i, height, exponent, theta_r, row_rad):
    """The 36 samples about the texel (row i, column 0) of a (height, 2 height) map: their u
    less the column's own u, v, weight and fractional mip level; and the weights' sum."""
    us = np.empty(36)
    vs = np.empty(36)
    ws = np.empty(36)
    ls = np.empty(36)
    width = 2 * height
    theta = math.pi * (i + 0.5) / height
    phi = math.pi / width  # column 0's centre, u = 0.5 / width
    st = math.sin(theta)
    rx = st * math.sin(phi)
    ry = math.cos(theta)
    rz = -st * math.cos(phi)
    tn = math.sqrt(rz * rz + rx * rx)  # t = y x r = (rz, 0, -rx) / |.|, b = r x t
    tx = rz / tn
    tz = -rx / tn
    bx = ry * tz
    by = rz * tx - rx * tz
    bz = -ry * tx
    total = 0.0
    n = 0
    for k in range(6):
        alpha = (k + 0.5) / 3.0 * theta_r
        ca = math.cos(alpha)
        sa = math.sin(alpha)
        w = math.exp(exponent * math.log(ca)) * sa if ca > 0.0 else 0.0
        if w <= 0.0:
            continue
        spacing = math.sqrt(alpha * theta_r / 3.0)
        level = math.log2(spacing / row_rad) if spacing > row_rad else 0.0
        for j in range(6):
            cp = _RING_COS[k % 2, j] * sa
            sp = _RING_SIN[k % 2, j] * sa
            u, v = _uv(ca * rx + cp * tx + sp * bx, ca * ry + sp * by, ca * rz + cp * tz + sp * bz)
            us[n] = u - 0.5 / width
            vs[n] = v
            ws[n] = w
            ls[n] = level
            total += w
            n += 1
    return us[:n], vs[:n], ws[:n], ls[:n], total


@register_jitable
def _accumulate_level(acc, data, offset, level_h, u0, v, weight, out_w):
    """acc[c] += weight * the bilinear lookup of one level at (u0 + (c + 0.5) / out_w, v)
    for every column c (u wraps, rows clamp): one sample of one row of the map. The level's
    width and out_w divide one another (both are pyramid levels' widths): fx takes one value
    per row, or one per phase of a coarser level's texel."""
    level_w = 2 * level_h
    y = v * level_h - 0.5
    y0f = math.floor(y)
    fy = y - y0f
    y0 = int(y0f)
    y1 = y0 + 1
    y0 = min(max(y0, 0), level_h - 1)
    y1 = min(max(y1, 0), level_h - 1)
    row0 = offset + y0 * level_w
    row1 = offset + y1 * level_w
    w0 = weight * (1.0 - fy)
    w1 = weight * fy
    step = level_w / out_w
    x_start = (u0 + 0.5 / out_w) * level_w - 0.5
    if level_w % out_w == 0:  # a level at least as fine as the map: one fx for the row
        istep = level_w // out_w
        x0f = math.floor(x_start)
        fx = x_start - x0f
        x0 = int(x0f) % level_w
        a = w0 * (1.0 - fx)
        b = w0 * fx
        e = w1 * (1.0 - fx)
        f = w1 * fx
        for c in range(out_w):
            x1 = x0 + 1
            if x1 == level_w:
                x1 = 0
            for ch in range(3):
                acc[c, ch] += (
                    a * data[row0 + x0, ch]
                    + b * data[row0 + x1, ch]
                    + e * data[row1 + x0, ch]
                    + f * data[row1 + x1, ch]
                )
            x0 += istep
            if x0 >= level_w:
                x0 -= level_w
        return
    m = out_w // level_w  # a coarser level: m columns per texel of it, m phases of fx
    for ph in range(m):
        xs = x_start + ph * step
        x0f = math.floor(xs)
        fx = xs - x0f
        x0 = int(x0f) % level_w
        a = w0 * (1.0 - fx)
        b = w0 * fx
        e = w1 * (1.0 - fx)
        f = w1 * fx
        for q in range(level_w):
            c = q * m + ph
            x1 = x0 + 1
            if x1 == level_w:
                x1 = 0
            for ch in range(3):
                acc[c, ch] += (
                    a * data[row0 + x0, ch]
                    + b * data[row0 + x1, ch]
                    + e * data[row1 + x0, ch]
                    + f * data[row1 + x1, ch]
                )
            x0 = x1


@numba.njit(parallel=True, cache=True, fastmath=True)
def _prefilter_cpu(exponent, theta_r, height, data, offsets, heights, out):
    """out (height, 2 height, 3): the glossy lobe of `exponent` about every texel centre."""
    width = 2 * height
    top = len(heights) - 1
    row_rad = math.pi / heights[0]
    for i in numba.prange(height):
        us, vs, ws, ls, total = _row_samples(i, height, exponent, theta_r, row_rad)
        acc = np.zeros((width, 3))
        for s in range(len(us)):
            level = min(max(ls[s], 0.0), float(top))
            l0 = min(int(math.floor(level)), top)
            f = level - l0
            _accumulate_level(
                acc, data, offsets[l0], heights[l0], us[s], vs[s], ws[s] * (1.0 - f), width
            )
            if f > 0.0:
                _accumulate_level(
                    acc, data, offsets[l0 + 1], heights[l0 + 1], us[s], vs[s], ws[s] * f, width
                )
        scale = 1.0 / total if total > 0.0 else 0.0
        for c in range(width):
            for ch in range(3):
                out[i, c, ch] = acc[c, ch] * scale


def prefiltered_map(pyramid: glossy.MipPyramid, exponent: float) -> np.ndarray:
    """(H, 2 H, 3) float32: the glossy radiance of Phong `exponent` about every texel centre
    of a map of :func:`prefilter_height` rows."""
    h = prefilter_height(pyramid, exponent)
    out = np.empty((h, 2 * h, 3), np.float32)
    _prefilter_cpu(
        float(exponent),
        glossy.lobe_radius_rad(exponent),
        h,
        pyramid.data,
        pyramid.offsets,
        pyramid.heights,
        out,
    )
    return out


# serial, as the other few-millisecond kernels: docs/results/ibl.md, "The 360 path ..."
@numba.njit(cache=True)
def _lookup_rows_cpu(directions, rows, data, height, out):
    """out[rows[i]] = the bilinear lookup of the map at directions[rows[i]]."""
    for q in range(rows.shape[0]):
        i = rows[q]
        u, v = _uv(directions[i, 0], directions[i, 1], directions[i, 2])
        r, g, b = _bilinear(data, 0, height, u, v)
        out[i, 0] = r
        out[i, 1] = g
        out[i, 2] = b


def lookup_rows(
    image: np.ndarray, directions: np.ndarray, rows: np.ndarray, out: np.ndarray
) -> None:
    """Fill out[rows] ((K, 3) float32) with the bilinear lookups of the (H, 2H, 3) map
    `image` at the unit `directions[rows]` ((K, 3) float64, C order)."""
    data = np.ascontiguousarray(image, dtype=np.float32).reshape(-1, 3)
    _lookup_rows_cpu(directions, np.ascontiguousarray(rows, np.int64), data, image.shape[0], out)


class PrefilteredMaps:
    """The prefiltered maps of one pyramid (one frame), each made on first use per exponent;
    prefilter_ms: the time spent making them."""

    def __init__(self, pyramid: glossy.MipPyramid):
        self.pyramid = pyramid
        self._maps: dict[float, np.ndarray] = {}
        self.prefilter_ms = 0.0

    def get(self, exponent: float) -> np.ndarray:
        """(H, 2 H, 3) float32: :func:`prefiltered_map` of `exponent`, made once."""
        key = float(exponent)
        if key not in self._maps:
            t0 = time.perf_counter()
            self._maps[key] = prefiltered_map(self.pyramid, key)
            self.prefilter_ms += (time.perf_counter() - t0) * 1e3
        return self._maps[key]


def specular(
    maps: PrefilteredMaps, directions: np.ndarray, modes: np.ndarray, exponents: np.ndarray
) -> np.ndarray:
    """``glossy.specular`` (CPU) with the glossy rows of each exponent looked up in its
    prefiltered map where :func:`worth_prefiltering` says so (the rest per pixel).

    directions (K, 3) unit mirror directions; modes (K,) 0 none / 1 mirror / 2 glossy;
    exponents (K,) Phong exponents (glossy rows). Returns (K, 3) float32 radiance.
    """
    d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(modes).reshape(-1)
    e = np.asarray(exponents, dtype=np.float64).reshape(-1)
    out = np.zeros((len(d), 3), np.float32)
    direct = m != 0
    glossy_rows = m == 2
    for n in np.unique(e[glossy_rows]):
        rows = np.flatnonzero(glossy_rows & (e == n))
        if worth_prefiltering(maps.pyramid, float(n), len(rows)):
            lookup_rows(maps.get(float(n)), d, rows, out)
            direct[rows] = False
    rest = np.flatnonzero(direct)
    if len(rest):
        out[rest] = glossy.specular(maps.pyramid, d[rest], m[rest], e[rest])
    return out
