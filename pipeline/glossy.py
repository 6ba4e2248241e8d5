"""Mirror and glossy reflection of an HDR equirectangular map by mipmap sampling (the 360
paper's sections 3.2 and 5, after Colbert and Krivanek).

Frame and mapping: ``pipeline/equirect.py`` (+y up, u = atan2(x, -z) / 2 pi, v = acos(y) / pi,
row 0 at the top; pixel centres at ((j + 0.5) / W, (i + 0.5) / H)).

The mip pyramid (:func:`mip_pyramid`). Level 0 is the HDR map itself (H x W, W = 2 H); level
k + 1 averages each 2 x 2 block of level k weighted by the exact solid angle of its two rows
(``equirect.row_solid_angles``), so every level keeps the map's integral over the sphere. A
GPU's box filter (and cv2.pyrDown, a 5-tap Gaussian of equal weights per row) weights a polar
row as much as an equatorial one, although it covers a smaller solid angle: near the poles
that over-weights the thinner row. The pyramid stops at 2 x 1 (or at the first odd height).

The glossy lobe (a Phong lobe about the mirror direction r): weight(w) = max(0, r . w)^n with
the exponent from the material's roughness rho by n = 2 / rho^2 - 2 (the usual Blinn-Phong
<-> Beckmann/GGX alpha relation: rho 0.01 -> n = 19998, rho 0.5 -> n = 6). The lobe radius
theta_r is where the weight is 0.5: cos(theta_r)^n = 0.5, theta_r = acos(0.5^(1/n))
(rho 0.01 -> 0.48 degrees, 0.1 -> 4.8, 0.5 -> 27). Glossy radiance is the lobe-weighted mean
G(r) = integral L(w) weight(w) dw / integral weight(w) dw.

The sampling pattern (fixed, 36 lookups of 2 bilinear taps each per pixel): 6 rings of 6
samples about r at angular radii alpha_k = (k + 0.5) / 3 theta_r, k = 0..5: three rings
inside the lobe (1/6, 1/2, 5/6 theta_r) and three outside (7/6, 3/2, 11/6 theta_r), odd rings
turned by 30 degrees. Each ring stands for the annulus of width theta_r / 3 about it (midpoint
rule in alpha), so a sample of ring k weighs cos(alpha_k)^n sin(alpha_k) (the Phong weight
times the annulus' solid angle per sample); the weights are normalised to sum 1. The lobe
beyond 2 theta_r (weight < 0.5^4, about 6 % of the lobe's integral for large n) is left out.

Mip level per ring: the angular spacing of its samples, the geometric mean of the chord
between neighbours on the ring (~ alpha_k) and the radial spacing theta_r / 3 (the side of the
square of the sample's solid angle, as Colbert and Krivanek's 0.5 log2(Omega_s / Omega_p)),
against the angular size of a row of level 0, pi / H: level = log2(spacing H / pi), clamped to
the pyramid. In a trial on the shared maps (the variants are not kept as code) this was better
overall than the larger of the two spacings; adding the equirect map's sin(theta) distortion
to the level, or a +0.5 / +1 level bias, was not better overall. Lookups are trilinear: bilinear
in levels floor(level) and floor(level) + 1 (wrapped across the u seam, rows clamped at the
poles, as ``equirect.sample_bilinear``), linear between them. Mirror reflection is one
bilinear lookup at level 0.

The per-sample logic is written once as ``register_jitable`` functions, driven by an
``@njit(parallel=True, cache=True)`` loop over pixels (``pipeline/glossy_prefilter.py``
drives the same pattern over the texels of a small map per frame, the renderer's fast
path); :func:`glossy_pattern_numpy` is the same pattern in plain NumPy (the oracle of the
kernel, used in tests), and :func:`glossy_brute_force` the full-resolution quadrature of the
same Phong lobe (the reference for the approximation's error, ``benchmarks/ibl_render.py``
and the tests).
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
from numba.extending import register_jitable

from arlight.pipeline import equirect
from arlight.pipeline.depth_filter import cuda_available  # the one probe of numba.cuda

ROUGHNESS_MIN = 0.01  # the paper's fig. 6 range
ROUGHNESS_MAX = 0.5
RINGS = 6  # 3 inside the lobe, 3 outside
RING_SAMPLES = 6


def check_roughness(roughness: float, field: str = "roughness") -> float:
    """`roughness` as a float in [ROUGHNESS_MIN, ROUGHNESS_MAX]; ValueError naming `field`."""
    r = float(roughness)
    if not (ROUGHNESS_MIN <= r <= ROUGHNESS_MAX):  # also refuses NaN
        raise ValueError(
            f"{field} must be in [{ROUGHNESS_MIN}, {ROUGHNESS_MAX}] for a glossy "
            f"lobe (the paper's fig. 6 range), got {roughness!r}"
        )
    return r


def phong_exponent(roughness: float) -> float:
    """Phong exponent n = 2 / rho^2 - 2 of roughness rho (checked to lie in 0.01..0.5)."""
    r = check_roughness(roughness)
    return 2.0 / (r * r) - 2.0


def lobe_radius_rad(exponent: float) -> float:
    """theta_r with cos(theta_r)^n = 0.5: the lobe's radius where the Phong weight is 0.5."""
    return math.acos(0.5 ** (1.0 / float(exponent)))


# --------------------------------------------------------------------------- the pyramid


class MipPyramid:
    """The levels of an HDR map, packed for the kernels.

    levels: list of (H_k, W_k, 3) float32 maps, H_k = H / 2^k; data: (sum H_k W_k, 3) float32,
    the levels one after another; offsets (L,) int64 row index of each level's first pixel;
    heights (L,) int64.
    """

    def __init__(self, levels: list[np.ndarray], data: np.ndarray | None = None):
        """levels: the maps, finest first; data: their packed rows when the caller has them
        already (``levels`` then views into it), else packed here (a copy)."""
        self.levels = levels
        self.heights = np.array([lv.shape[0] for lv in levels], np.int64)
        self.offsets = _level_offsets(self.heights)
        if data is None:
            data = np.concatenate([lv.reshape(-1, 3) for lv in levels]).astype(np.float32)
        self.data = data

    @property
    def num_levels(self) -> int:
        return len(self.levels)


def downsample_2x2(level: np.ndarray) -> np.ndarray:
    """One pyramid step: each 2 x 2 block averaged with its two rows' exact solid angles."""
    h, w = level.shape[:2]
    omega = equirect.row_solid_angles(h, w).astype(np.float64)
    pair = omega.reshape(h // 2, 2)
    weights = (pair / pair.sum(axis=1, keepdims=True)).astype(np.float32)  # (h/2, 2)
    blocks = level.reshape(h // 2, 2, w // 2, 2, -1).astype(np.float32)
    rows = (
        blocks[:, 0] * weights[:, 0, None, None, None]
        + blocks[:, 1] * weights[:, 1, None, None, None]
    )
    return 0.5 * (rows[:, :, 0] + rows[:, :, 1])


def _level_offsets(heights: np.ndarray) -> np.ndarray:
    """(L,) int64: the first packed row of each level of heights H_k (widths 2 H_k)."""
    sizes = 2 * heights * heights
    return np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)


@numba.njit(cache=True)
def _copy_radiance(values, out):
    """out[k] = values[k] (flat) as float32, non-finite or negative values as 0."""
    for k in range(values.shape[0]):
        v = np.float32(values[k])
        out[k] = v if (v > 0.0 and v < np.inf) else np.float32(0.0)  # NaN compares False


# serial (a few ms; 2 threads lose under load): docs/results/ibl.md, "The 360 path ..."
@numba.njit(cache=True)
def _downsample_packed(data, src, dst, height, weights):
    """Level of `height` / 2 rows at packed row `dst` from the level of `height` rows at
    `src`: each 2 x 2 block, its rows weighted by weights (height / 2, 2) float32, the
    columns averaged (float32 throughout, the arithmetic of ``downsample_2x2``)."""
    w = 2 * height
    half = np.float32(0.5)
    for i in range(height // 2):
        w0 = weights[i, 0]
        w1 = weights[i, 1]
        top = src + 2 * i * w
        bottom = top + w
        out = dst + i * (w // 2)
        for j in range(w // 2):
            for c in range(3):
                a = data[top + 2 * j, c] * w0 + data[bottom + 2 * j, c] * w1
                b = data[top + 2 * j + 1, c] * w0 + data[bottom + 2 * j + 1, c] * w1
                data[out + j, c] = half * (a + b)


@functools.lru_cache(maxsize=32)
def _pair_weights(height: int) -> np.ndarray:
    """(height / 2, 2) float32: the two rows' shares of each block row (``downsample_2x2``)."""
    omega = equirect.row_solid_angles(height, 2 * height).astype(np.float64)
    pair = omega.reshape(height // 2, 2)
    out = (pair / pair.sum(axis=1, keepdims=True)).astype(np.float32)
    out.setflags(write=False)
    return out


def packed_rows(height: int) -> int:
    """Rows (texels) of the packed pyramid of an (height, 2 height) map."""
    heights = [int(height)]
    while heights[-1] >= 2 and heights[-1] % 2 == 0:
        heights.append(heights[-1] // 2)
    return sum(2 * h * h for h in heights)


def mip_pyramid(hdr: np.ndarray, buffer: np.ndarray | None = None) -> MipPyramid:
    """The area-correct mip pyramid of an (H, W, 3) linear HDR equirectangular map (level 0 =
    the map as float32; non-finite or negative radiance taken as 0).

    Built in place in the packed array (Numba, one pass per level): the same values as
    ``downsample_2x2`` level by level. buffer: a C-contiguous (N, 3) float32 array with N >=
    ``packed_rows(H)`` to build in instead of a new one (a caller that renders frame after
    frame and drops each pyramid before the next: no fresh pages to fault in per frame)."""
    image = equirect.check_equirect(hdr, "hdr")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"hdr: expected an (H, W, 3) RGB map, got shape {image.shape}")
    heights = [image.shape[0]]
    while heights[-1] >= 2 and heights[-1] % 2 == 0:
        heights.append(heights[-1] // 2)
    h_arr = np.array(heights, np.int64)
    offsets = _level_offsets(h_arr)
    rows = int(2 * (h_arr * h_arr).sum())
    usable = (
        buffer is not None
        and buffer.dtype == np.float32
        and buffer.ndim == 2
        and buffer.shape[0] >= rows
        and buffer.shape[1] == 3
        and buffer.flags.c_contiguous
    )
    data = buffer[:rows] if usable and buffer is not None else np.empty((rows, 3), np.float32)
    src = image if image.dtype in (np.float32, np.float64) else image.astype(np.float32)
    _copy_radiance(
        np.ascontiguousarray(src).reshape(-1), data[: heights[0] * 2 * heights[0]].reshape(-1)
    )
    for k in range(len(heights) - 1):
        _downsample_packed(data, offsets[k], offsets[k + 1], heights[k], _pair_weights(heights[k]))
    levels = [
        data[o : o + 2 * h * h].reshape(h, 2 * h, 3) for o, h in zip(offsets, heights, strict=True)
    ]
    return MipPyramid(levels, data)


# --------------------------------------------------------------------------- per-sample logic

# cos / sin of the samples' angles about r: (j + 0.5 (k % 2)) 60 degrees, even / odd rings
_RING_PHI = (np.arange(RING_SAMPLES)[None, :] + 0.5 * np.arange(2)[:, None]) * (math.pi / 3.0)
_RING_COS = np.cos(_RING_PHI)
_RING_SIN = np.sin(_RING_PHI)


@register_jitable
def _bilinear(data, offset, height, u, v):
    """The bilinear lookup (r, g, b) of the level at (u, v) (u wraps, rows clamp)."""
    width = 2 * height
    x = u * width - 0.5
    y = v * height - 0.5
    x0f = math.floor(x)
    y0f = math.floor(y)
    fx = x - x0f
    fy = y - y0f
    x0 = int(x0f)
    if x0 < 0:
        x0 += width
    elif x0 >= width:
        x0 -= width
    x1 = x0 + 1
    if x1 >= width:
        x1 = 0
    y0 = int(y0f)
    y1 = y0 + 1
    if y0 < 0:
        y0 = 0
    if y1 < 0:
        y1 = 0
    if y0 > height - 1:
        y0 = height - 1
    if y1 > height - 1:
        y1 = height - 1
    w00 = (1.0 - fx) * (1.0 - fy)
    w01 = fx * (1.0 - fy)
    w10 = (1.0 - fx) * fy
    w11 = fx * fy
    i00 = offset + y0 * width + x0
    i01 = offset + y0 * width + x1
    i10 = offset + y1 * width + x0
    i11 = offset + y1 * width + x1
    r = w00 * data[i00, 0] + w01 * data[i01, 0] + w10 * data[i10, 0] + w11 * data[i11, 0]
    g = w00 * data[i00, 1] + w01 * data[i01, 1] + w10 * data[i10, 1] + w11 * data[i11, 1]
    b = w00 * data[i00, 2] + w01 * data[i01, 2] + w10 * data[i10, 2] + w11 * data[i11, 2]
    return r, g, b


@register_jitable
def _uv(dx, dy, dz):
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    y = dy / n
    if y > 1.0:
        y = 1.0
    if y < -1.0:
        y = -1.0
    u = math.atan2(dx, -dz) / (2.0 * math.pi)
    if u < 0.0:
        u += 1.0
    return u, math.acos(y) / math.pi


@register_jitable
def _trilinear(data, offsets, heights, num_levels, u, v, level):
    """The trilinear lookup (r, g, b) at (u, v) and fractional `level`."""
    if level <= 0.0:
        return _bilinear(data, offsets[0], heights[0], u, v)
    top = num_levels - 1
    if level >= top:
        return _bilinear(data, offsets[top], heights[top], u, v)
    l0 = int(math.floor(level))
    f = level - l0
    r0, g0, b0 = _bilinear(data, offsets[l0], heights[l0], u, v)
    r1, g1, b1 = _bilinear(data, offsets[l0 + 1], heights[l0 + 1], u, v)
    return (r0 + f * (r1 - r0), g0 + f * (g1 - g0), b0 + f * (b1 - b0))


@register_jitable
def _glossy_pixel(rx, ry, rz, exponent, theta_r, data, offsets, heights, num_levels):
    """The glossy radiance (r, g, b) about the unit mirror direction r (the module text)."""
    sum_r = 0.0
    sum_g = 0.0
    sum_b = 0.0
    # an orthonormal frame (t, b) about r
    if abs(ry) < 0.9:
        ax, ay, az = 0.0, 1.0, 0.0
    else:
        ax, ay, az = 1.0, 0.0, 0.0
    tx = ay * rz - az * ry
    ty = az * rx - ax * rz
    tz = ax * ry - ay * rx
    tn = math.sqrt(tx * tx + ty * ty + tz * tz)
    tx /= tn
    ty /= tn
    tz /= tn
    bx = ry * tz - rz * ty
    by = rz * tx - rx * tz
    bz = rx * ty - ry * tx
    row_rad = math.pi / heights[0]
    total = 0.0
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
            dx = ca * rx + cp * tx + sp * bx
            dy = ca * ry + cp * ty + sp * by
            dz = ca * rz + cp * tz + sp * bz
            u, v = _uv(dx, dy, dz)
            cr, cg, cb = _trilinear(data, offsets, heights, num_levels, u, v, level)
            sum_r += w * cr
            sum_g += w * cg
            sum_b += w * cb
            total += w
    if total > 0.0:
        return sum_r / total, sum_g / total, sum_b / total
    return 0.0, 0.0, 0.0


@numba.njit(parallel=True, cache=True)
def _specular_cpu(directions, modes, exponents, radii, data, offsets, heights, out):
    """Per pixel: mode 1 = mirror (one lookup at level 0), 2 = glossy, 0 = none (zeros)."""
    num_levels = len(heights)
    for i in numba.prange(directions.shape[0]):
        r, g, b = 0.0, 0.0, 0.0
        if modes[i] == 1:
            u, v = _uv(directions[i, 0], directions[i, 1], directions[i, 2])
            r, g, b = _bilinear(data, offsets[0], heights[0], u, v)
        elif modes[i] == 2:
            r, g, b = _glossy_pixel(
                directions[i, 0],
                directions[i, 1],
                directions[i, 2],
                exponents[i],
                radii[i],
                data,
                offsets,
                heights,
                num_levels,
            )
        out[i, 0] = r
        out[i, 1] = g
        out[i, 2] = b


@numba.njit(parallel=True, cache=True)
def _lookup_cpu(directions, data, height, out):
    for i in numba.prange(directions.shape[0]):
        u, v = _uv(directions[i, 0], directions[i, 1], directions[i, 2])
        r, g, b = _bilinear(data, 0, height, u, v)
        out[i, 0] = r
        out[i, 1] = g
        out[i, 2] = b


def lookup(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Bilinear lookup (K, 3) float32 of an (H, W, 3) equirectangular map at unit
    `directions` (K, 3), as ``equirect.sample_bilinear`` (which OpenCV limits to 32767
    lookups per call) in the kernels' own code."""
    image = equirect.check_equirect(image, "image")
    data = np.ascontiguousarray(image, dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(d), 3), np.float32)
    _lookup_cpu(d, data, image.shape[0], out)
    return out


def _unit_rows(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    if not np.all(n > 0) or not np.all(np.isfinite(d)):
        raise ValueError("directions must be finite and non-zero")
    return np.ascontiguousarray(d / n)


def glossy(pyramid: MipPyramid, directions: np.ndarray, roughness: float) -> np.ndarray:
    """Glossy radiance (..., 3) float32 about the mirror `directions` (..., 3), one roughness
    in [0.01, 0.5] (the Numba kernel)."""
    shape = np.shape(directions)[:-1]
    d = _unit_rows(directions)
    n = phong_exponent(roughness)
    out = np.zeros((len(d), 3), np.float32)
    _specular_cpu(  # every row glossy (mode 2)
        d,
        np.full(len(d), 2, np.int64),
        np.full(len(d), n),
        np.full(len(d), lobe_radius_rad(n)),
        pyramid.data,
        pyramid.offsets,
        pyramid.heights,
        out,
    )
    return out.reshape(*shape, 3)


def specular(
    pyramid: MipPyramid,
    directions: np.ndarray,
    modes: np.ndarray,
    exponents: np.ndarray,
    backend: str = "cpu",
) -> np.ndarray:
    """Per row: mirror (mode 1), glossy with its Phong exponent (mode 2) or 0 (mode 0).

    directions (K, 3) unit mirror directions; modes (K,) int; exponents (K,) float64 (used
    where mode is 2); backend "cpu" (Numba, parallel) or "cuda" (numba.cuda, the same
    per-pixel code; RuntimeError where no GPU is visible). Returns (K, 3) float32 radiance.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "cuda" and not cuda_available():
        raise RuntimeError("backend='cuda' requested but numba.cuda sees no GPU; use backend='cpu'")
    d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    exps = np.ascontiguousarray(exponents, dtype=np.float64).reshape(-1)
    safe = np.where(exps > 0, exps, 1.0)
    radii = np.arccos(np.power(0.5, 1.0 / safe))
    m = np.ascontiguousarray(modes, dtype=np.int64).reshape(-1)
    out = np.zeros((len(d), 3), np.float32)
    if backend == "cuda":
        return _specular_cuda(d, m, safe, radii, pyramid, out)
    _specular_cpu(d, m, safe, radii, pyramid.data, pyramid.offsets, pyramid.heights, out)
    return out


BACKENDS = ("cpu", "cuda")
_CUDA_BLOCK = 128


cuda = None  # numba.cuda, bound on first use (a module global, as depth_filter's)


@functools.cache
def _cuda_kernel():
    """The CUDA driver of the per-pixel logic above (built on first use)."""
    global cuda
    from numba import cuda

    @cuda.jit
    def specular_kernel(directions, modes, exponents, radii, data, offsets, heights, out):
        i = cuda.grid(1)
        if i < directions.shape[0]:
            r, g, b = 0.0, 0.0, 0.0
            if modes[i] == 1:
                u, v = _uv(directions[i, 0], directions[i, 1], directions[i, 2])
                r, g, b = _bilinear(data, offsets[0], heights[0], u, v)
            elif modes[i] == 2:
                r, g, b = _glossy_pixel(
                    directions[i, 0],
                    directions[i, 1],
                    directions[i, 2],
                    exponents[i],
                    radii[i],
                    data,
                    offsets,
                    heights,
                    heights.shape[0],
                )
            out[i, 0] = r
            out[i, 1] = g
            out[i, 2] = b

    return specular_kernel


def _specular_cuda(d, modes, exponents, radii, pyramid: MipPyramid, out):
    kernel = _cuda_kernel()
    args = [
        cuda.to_device(a)
        for a in (d, modes, exponents, radii, pyramid.data, pyramid.offsets, pyramid.heights, out)
    ]
    grid = max(1, (len(d) + _CUDA_BLOCK - 1) // _CUDA_BLOCK)
    kernel[grid, _CUDA_BLOCK](*args)
    cuda.synchronize()
    return args[-1].copy_to_host()


def mirror(pyramid: MipPyramid, directions: np.ndarray) -> np.ndarray:
    """Mirror radiance (..., 3): one bilinear lookup at level 0."""
    return equirect.sample_bilinear(pyramid.levels[0], np.asarray(directions))


# --------------------------------------------------------------------------- oracles


def _pattern(
    directions: np.ndarray, exponent: float, frame: str = "switch"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ring pattern: sample directions (K, 36, 3), weights (36,) summing to 1, angular
    spacings (36,) (radians, giving the levels), as the kernel makes them. frame "switch":
    t = normalize(a x r) with a = y, or x where |r.y| >= 0.9 (this module's kernel); "y":
    a = y always (``glossy_prefilter``'s maps)."""
    d = _unit_rows(directions)
    theta_r = lobe_radius_rad(exponent)
    limit = 0.9 if frame == "switch" else math.inf
    axis = np.where(np.abs(d[:, 1:2]) < limit, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(axis, d)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(d, t)
    k = np.repeat(np.arange(RINGS), RING_SAMPLES)
    j = np.tile(np.arange(RING_SAMPLES), RINGS)
    alpha = (k + 0.5) / 3.0 * theta_r
    phi = (j + 0.5 * (k % 2)) * (math.pi / 3.0)
    dirs = (
        np.cos(alpha)[None, :, None] * d[:, None, :]
        + (np.sin(alpha) * np.cos(phi))[None, :, None] * t[:, None, :]
        + (np.sin(alpha) * np.sin(phi))[None, :, None] * b[:, None, :]
    )
    w = np.power(np.cos(alpha), exponent) * np.sin(alpha)
    spacing = np.sqrt(alpha * theta_r / 3.0)
    return dirs, w / w.sum(), spacing


def glossy_pattern_numpy(
    pyramid: MipPyramid, directions: np.ndarray, roughness: float, frame: str = "switch"
) -> np.ndarray:
    """The kernel's pattern in plain NumPy with ``equirect.sample_bilinear`` per level (the
    oracle of :func:`glossy`, and with frame "y" of ``glossy_prefilter``'s maps; slow)."""
    if frame not in ("switch", "y"):
        raise ValueError(f"frame must be 'switch' or 'y', got {frame!r}")
    n = phong_exponent(roughness)
    dirs, w, spacing = _pattern(directions, n, frame)
    row_rad = math.pi / pyramid.levels[0].shape[0]
    level = np.where(spacing > row_rad, np.log2(np.maximum(spacing, row_rad) / row_rad), 0.0)
    level = np.clip(level, 0.0, pyramid.num_levels - 1)
    out = np.zeros((dirs.shape[0], 3))
    for s in range(dirs.shape[1]):
        l0 = int(math.floor(level[s]))
        f = level[s] - l0
        value = (1.0 - f) * equirect.sample_bilinear(pyramid.levels[l0], dirs[:, s])
        if f > 0.0:
            value = value + f * equirect.sample_bilinear(pyramid.levels[l0 + 1], dirs[:, s])
        out += w[s] * value
    return out.astype(np.float32).reshape(*np.shape(directions)[:-1], 3)


def glossy_brute_force(
    hdr: np.ndarray, directions: np.ndarray, roughness: float, batch: int = 8
) -> np.ndarray:
    """The reference: G(r) = sum_p L_p max(0, r . w_p)^n d_omega_p / sum_p max(0, r . w_p)^n
    d_omega_p over every pixel p of the full-resolution map (pixel centres, exact solid
    angles). (K, 3) float64. Below rho ~ 0.02 the lobe is only a few pixels of a 1k map wide
    and this quadrature is itself coarse."""
    image = equirect.check_equirect(hdr, "hdr")
    h, w = image.shape[:2]
    n = phong_exponent(roughness)
    pix = equirect.pixel_directions(h, w).reshape(-1, 3)
    omega = equirect.pixel_solid_angles(h, w).reshape(-1)
    values = np.asarray(image, dtype=np.float64).reshape(-1, 3)
    d = _unit_rows(directions)
    out = np.zeros((len(d), 3))
    for start in range(0, len(d), batch):
        cos = np.maximum(d[start : start + batch] @ pix.T, 0.0)
        weight = np.power(cos, n) * omega
        out[start : start + batch] = (weight @ values) / weight.sum(axis=1, keepdims=True)
    return out
