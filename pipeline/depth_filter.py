"""Image-space depth filter chain D' -> D'' -> D''' and normals (seeds/000, section 4).

Inputs, all (H, W) and pixel-aligned:

- ``depth_raw_m``  D_c: the sensor depth, float32 metres, 0 (or NaN on entry) = missing.
- ``depth_volume_m`` D_v: the volume ray-cast into the current view, same convention.
- ``intensity``    I_c: grey levels 0..255 (float32), see :func:`intensity_from_rgb`.

Passes (parameters of section 6.1 are the defaults):

- D'  :func:`merge_depth` (eq. 1-3), k=20, lambda_I=7, lambda_D=5 cm.
- D'' :func:`joint_bilateral_median` (eq. 4), k=8 sub-sampled to 5x5, lambda_I=7.
- D''':func:`median_depth` (eq. 5), k=2.

Conventions shared by every pass:

- A k x k window around pixel (y, x) covers offsets ``-k//2 .. k - k//2 - 1`` on each axis
  (k=2: -1..0; k=8: -4..3; k=20: -10..9), clipped at the image borders.
- Missing depth (0) is never part of a support set.
- "median" is the LOWER median, the sample of rank ``(n - 1) // 2`` among the n sorted
  values: it is always a measured depth and never invents a depth halfway across an edge
  (the mean of the two middle samples would create flying pixels between two surfaces).
- A pixel whose support set is empty gets 0 (missing), except in D' (see below).

Decisions where the paper leaves room (eq. 3):

- ``|D_c - D_v| == lambda_D`` counts as "moved" (D_c is kept); agreement is strict ``<``.
- A hole (D_c missing) takes D_v(p) when D_v(p) exists, Omega_I(p) is not empty and
  ``|Omega_D| >= |Omega_I| / 2``; otherwise the median of D_c over Omega_I when Omega_I is
  not empty; otherwise (no support at all) D_v(p) when it exists, else 0. A hole whose
  support agrees with the volume but where D_v(p) itself is missing gets the median.
- Omega_D requires D_v(q) to exist (a support pixel without volume depth cannot agree).

Backends (docs/architecture.md, "Conventions"): the per-pixel logic is written once as
``register_jitable`` functions (``_merge_pixel``, ``_support_median_pixel``,
``_normal_pixel``), driven on the CPU by ``@njit(parallel=True, cache=True)`` loops over
rows and on the GPU by ``numba.cuda`` kernels that are built on first use (importing this
module never touches CUDA). Every public function takes ``backend="cpu"`` or ``"cuda"``;
asking for CUDA where :func:`cuda_available` is False raises ``RuntimeError`` (no silent
fallback). Both backends select the same float32 samples with the same float32 comparisons,
so the depth passes agree bit for bit; normals agree to float32 rounding (~1e-6).

On the CPU, D'' and D''' with up to 32 candidates a pixel run a row of pixels at a time
through a selection network (:mod:`arlight.pipeline.median_network`), bit for bit the per-
pixel kernel's result. Medians inside the per-pixel kernels use a scratch buffer
(``np.empty`` per row on the CPU, ``cuda.local.array`` per thread on the GPU): up to 32
samples (D''': 4, D'': up to 25) the one whose count of smaller samples is <= k < its count
of smaller-or-equal ones (O(n^2) compares without branches: D'' in half the time of Wirth's
selection), Wirth's in-place selection above (a D' hole: up to k*k = 400; O(n) on average,
no recursion). A D' hole skips the rows of its window that hold no measured depth (an
integral image of D_c > 0 counts them) and stops as soon as the volume-agreeing majority is
certain, whatever the samples left may hold; a hole with no measured depth in its window is
answered at once.

Slow NumPy references (``_*_reference``) mirror each kernel and serve as test oracles only.
"""

from __future__ import annotations

import functools
import math

import cv2
import numba
import numpy as np
from numba import prange
from numba.extending import register_jitable

from arlight.core.camera import PinholeCamera
from arlight.core.checks import CheckError, check_image
from arlight.pipeline.config import MAX_WINDOW, FilterParams
from arlight.pipeline.median_network import (
    MAX_NETWORK_INPUTS,
    median_network,
    support_median_rows,
)

__all__ = [
    "BACKENDS",
    "MAX_WINDOW",
    "cuda_available",
    "filter_depth",
    "joint_bilateral_median",
    "median_depth",
    "merge_depth",
    "normals_from_depth",
]

BACKENDS = ("cpu", "cuda")
NORMAL_MAX_RELATIVE_JUMP = 0.05  # a neighbour further than 5 % of the depth is another surface
_CUDA_BLOCK = (16, 16)
_RANK_SELECT = 32  # medians of up to this many samples by counting ranks (O(n^2), no branches)


# --------------------------------------------------------------------------------------
# Per-pixel logic, shared by the CPU and CUDA drivers
# --------------------------------------------------------------------------------------


@register_jitable
def _lower_median(buf, n):
    """Sample of rank (n - 1) // 2 of buf[:n] (n >= 1); may reorder buf.

    Up to _RANK_SELECT samples by counting ranks (the sample with fewer than k + 1 smaller
    and more than k smaller-or-equal ones: branch-free inner loops, twice as fast as a
    selection for the 25 samples of D''), Wirth's in-place selection above."""
    kth = (n - 1) // 2
    if n <= _RANK_SELECT:
        for i in range(n):
            v = buf[i]
            less = 0
            leq = 0
            for j in range(n):
                less += buf[j] < v
                leq += buf[j] <= v
            if less <= kth < leq:
                return v
        return buf[kth]  # not reached: some sample holds the rank
    lo = 0
    hi = n - 1
    while lo < hi:
        pivot = buf[kth]
        i = lo
        j = hi
        while True:
            while buf[i] < pivot:
                i += 1
            while pivot < buf[j]:
                j -= 1
            if i <= j:
                tmp = buf[i]
                buf[i] = buf[j]
                buf[j] = tmp
                i += 1
                j -= 1
            if i > j:
                break
        if j < kth:
            lo = i
        if kth < i:
            hi = j
    return buf[kth]


@register_jitable
def _window_count(valid_sum, y0, y1, x0, x1):
    """Valid samples in rows y0..y1-1, columns x0..x1-1, from the integral image."""
    return valid_sum[y1, x1] - valid_sum[y0, x1] - valid_sum[y1, x0] + valid_sum[y0, x0]


@register_jitable
def _merge_pixel(depth_c, depth_v, intensity, valid_sum, y, x, k, lam_i, lam_d, scratch):
    """D'(y, x) of eq. 3; scratch holds >= k*k float32 samples; valid_sum (H+1, W+1) is the
    integral image of D_c > 0, so that windows and rows without a measured depth are
    skipped (the result is the same as scanning them)."""
    dc = depth_c[y, x]
    dv = depth_v[y, x]
    if dc > 0:
        if dv > 0 and abs(dc - dv) < lam_d:
            return dv
        return dc
    h, w = depth_c.shape
    y0 = max(y - k // 2, 0)
    y1 = min(y - k // 2 + k, h)
    x0 = max(x - k // 2, 0)
    x1 = min(x - k // 2 + k, w)
    left = _window_count(valid_sum, y0, y1, x0, x1)  # measured samples not yet scanned
    if left == 0:  # no support at all
        return dv if dv > 0 else dc
    ip = intensity[y, x]
    n_i = 0  # |Omega_I|
    n_d = 0  # |Omega_D|
    for qy in range(y0, y1):
        in_row = _window_count(valid_sum, qy, qy + 1, x0, x1)
        if in_row == 0:
            continue
        left -= in_row
        for qx in range(x0, x1):
            dq = depth_c[qy, qx]
            if dq > 0 and abs(ip - intensity[qy, qx]) < lam_i:
                scratch[n_i] = dq
                n_i += 1
                vq = depth_v[qy, qx]
                if vq > 0 and abs(dq - vq) < lam_d:
                    n_d += 1
        # Early out: the majority already agrees, whatever the samples left may hold.
        if dv > 0 and n_i > 0 and 2 * n_d >= n_i + left:
            return dv
    if n_i > 0:
        if dv > 0 and 2 * n_d >= n_i:
            return dv
        return _lower_median(scratch, n_i)
    if dv > 0:
        return dv
    return dc  # missing: 0


@register_jitable
def _support_median_pixel(depth, intensity, y, x, offsets, lam_i, gate, scratch):
    """Lower median of valid depth at (y + oy, x + ox), oy, ox in offsets; when gate, only
    where |I(p) - I(q)| < lam_i (eq. 4), else all of them (eq. 5). 0 if none."""
    h, w = depth.shape
    ip = intensity[y, x]
    n = 0
    for a in range(offsets.shape[0]):
        qy = y + offsets[a]
        if qy < 0 or qy >= h:
            continue
        for b in range(offsets.shape[0]):
            qx = x + offsets[b]
            if qx < 0 or qx >= w:
                continue
            dq = depth[qy, qx]
            if dq > 0 and (not gate or abs(ip - intensity[qy, qx]) < lam_i):
                scratch[n] = dq
                n += 1
    if n == 0:
        return np.float32(0.0)
    return _lower_median(scratch, n)


@register_jitable
def _continuous(z, zq, max_jump):
    return zq > 0 and abs(zq - z) <= max_jump * z


@register_jitable
def _normal_pixel(depth, y, x, fx, fy, cx, cy, max_jump):
    """Unit normal (nx, ny, nz) at (y, x) facing the camera, or (0, 0, 0)."""
    h, w = depth.shape
    z = float(depth[y, x])
    if not z > 0:
        return 0.0, 0.0, 0.0
    right = x + 1 < w and _continuous(z, float(depth[y, x + 1]), max_jump)
    left = x >= 1 and _continuous(z, float(depth[y, x - 1]), max_jump)
    down = y + 1 < h and _continuous(z, float(depth[y + 1, x]), max_jump)
    up = y >= 1 and _continuous(z, float(depth[y - 1, x]), max_jump)
    if not (right or left) or not (down or up):
        return 0.0, 0.0, 0.0
    xa = x + 1 if right else x
    xb = x - 1 if left else x
    ya = y + 1 if down else y
    yb = y - 1 if up else y
    za = float(depth[y, xa])
    zb = float(depth[y, xb])
    # tangent along image x: P(y, xa) - P(y, xb)
    tx0 = (xa - cx) / fx * za - (xb - cx) / fx * zb
    tx1 = (y - cy) / fy * (za - zb)
    tx2 = za - zb
    za = float(depth[ya, x])
    zb = float(depth[yb, x])
    # tangent along image y: P(ya, x) - P(yb, x)
    ty0 = (x - cx) / fx * (za - zb)
    ty1 = (ya - cy) / fy * za - (yb - cy) / fy * zb
    ty2 = za - zb
    n0 = tx1 * ty2 - tx2 * ty1
    n1 = tx2 * ty0 - tx0 * ty2
    n2 = tx0 * ty1 - tx1 * ty0
    norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not norm > 0:
        return 0.0, 0.0, 0.0
    # orient towards the camera: n . P(y, x) < 0
    if n0 * ((x - cx) / fx * z) + n1 * ((y - cy) / fy * z) + n2 * z > 0:
        norm = -norm
    return n0 / norm, n1 / norm, n2 / norm


# --------------------------------------------------------------------------------------
# CPU drivers
# --------------------------------------------------------------------------------------


@numba.njit(parallel=True, cache=True)
def _merge_cpu(depth_c, depth_v, intensity, valid_sum, k, lam_i, lam_d, out):
    h, w = out.shape
    for row in prange(h):
        y = np.int64(row)  # prange may type its index unsigned; int64 keeps the index maths
        scratch = np.empty(k * k, np.float32)
        for x in range(w):
            out[y, x] = _merge_pixel(
                depth_c, depth_v, intensity, valid_sum, y, x, k, lam_i, lam_d, scratch
            )


@numba.njit(parallel=True, cache=True)
def _support_median_cpu(depth, intensity, offsets, lam_i, gate, out):
    h, w = out.shape
    n = offsets.shape[0]
    for row in prange(h):
        y = np.int64(row)
        scratch = np.empty(n * n, np.float32)
        for x in range(w):
            out[y, x] = _support_median_pixel(depth, intensity, y, x, offsets, lam_i, gate, scratch)


@numba.njit(parallel=True, cache=True)
def _normals_cpu(depth, fx, fy, cx, cy, max_jump, out):
    h, w = depth.shape
    for row in prange(h):
        y = np.int64(row)
        for x in range(w):
            n0, n1, n2 = _normal_pixel(depth, y, x, fx, fy, cx, cy, max_jump)
            out[y, x, 0] = n0
            out[y, x, 1] = n1
            out[y, x, 2] = n2


# --------------------------------------------------------------------------------------
# CUDA drivers (built on first use)
# --------------------------------------------------------------------------------------


def cuda_available() -> bool:
    """True when numba.cuda can be imported and sees a usable GPU (or its simulator)."""
    try:
        from numba import cuda
    except Exception:  # any import failure means no CUDA backend
        return False
    try:
        return bool(cuda.is_available())
    except Exception:  # a broken driver means no CUDA backend
        return False


cuda = None  # numba.cuda, bound on first use by _cuda_kernels (a module global, so that the
# CUDA simulator can swap it inside the kernels as it does for any kernel module)


@functools.cache
def _cuda_kernels(scratch_size: int):
    """The CUDA kernels with a per-thread scratch of `scratch_size` float32 (a constant)."""
    global cuda
    from numba import cuda

    @cuda.jit
    def merge(depth_c, depth_v, intensity, valid_sum, k, lam_i, lam_d, out):
        x, y = cuda.grid(2)
        if y < out.shape[0] and x < out.shape[1]:
            scratch = cuda.local.array(scratch_size, np.float32)
            out[y, x] = _merge_pixel(
                depth_c, depth_v, intensity, valid_sum, y, x, k, lam_i, lam_d, scratch
            )

    @cuda.jit
    def support_median(depth, intensity, offsets, lam_i, gate, out):
        x, y = cuda.grid(2)
        if y < out.shape[0] and x < out.shape[1]:
            scratch = cuda.local.array(scratch_size, np.float32)
            out[y, x] = _support_median_pixel(depth, intensity, y, x, offsets, lam_i, gate, scratch)

    @cuda.jit
    def normals(depth, fx, fy, cx, cy, max_jump, out):
        x, y = cuda.grid(2)
        if y < depth.shape[0] and x < depth.shape[1]:
            n0, n1, n2 = _normal_pixel(depth, y, x, fx, fy, cx, cy, max_jump)
            out[y, x, 0] = n0
            out[y, x, 1] = n1
            out[y, x, 2] = n2

    return merge, support_median, normals


def _scratch_size(n: int) -> int:
    """Round the scratch size up to a power of two (>= 16) so few kernel variants compile."""
    size = 16
    while size < n:
        size *= 2
    return size


def _cuda_launch(kernel_index: int, scratch: int, shape: tuple[int, int], *args):
    kernel = _cuda_kernels(_scratch_size(scratch))[kernel_index]
    h, w = shape
    grid = ((w + _CUDA_BLOCK[0] - 1) // _CUDA_BLOCK[0], (h + _CUDA_BLOCK[1] - 1) // _CUDA_BLOCK[1])
    device_args = [cuda.to_device(a) if isinstance(a, np.ndarray) else a for a in args]
    kernel[grid, _CUDA_BLOCK](*device_args)
    cuda.synchronize()
    return device_args[-1].copy_to_host()


# --------------------------------------------------------------------------------------
# Validation and dispatch
# --------------------------------------------------------------------------------------


def _check_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "cuda" and not cuda_available():
        raise RuntimeError("backend='cuda' requested but numba.cuda sees no GPU; use backend='cpu'")
    return backend


def _check_depth(
    name: str,
    depth: np.ndarray,
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """(H, W) float32 copy-free where possible, NaN -> 0; rejects other shapes, inf, < 0."""
    arr = check_image(depth, name)  # (H, W)
    if shape is not None and arr.shape != shape:
        raise CheckError(name, f"expected shape {shape} (same as depth_raw_m), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise CheckError(name, f"expected a float dtype (metres, float32), got {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    nan = np.isnan(arr)
    if nan.any():
        arr = np.where(nan, np.float32(0.0), arr)
    bad = np.isinf(arr) | (arr < 0)
    if bad.any():
        raise CheckError(
            name,
            f"depth must be finite and >= 0 metres (0 or NaN = missing); "
            f"{int(bad.sum())} pixel(s) are inf or negative",
        )
    return arr


def _check_intensity(intensity: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    arr = np.asarray(intensity)
    if arr.shape != shape:
        raise CheckError(
            "intensity", f"expected shape {shape} (same as the depth), got {arr.shape}"
        )
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise CheckError("intensity", f"expected grey levels as float32, got {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        raise CheckError("intensity", "expected finite grey levels, got NaN or inf")
    return arr


def _check_window(name: str, value: int) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not 1 <= value <= MAX_WINDOW
    ):
        raise CheckError(name, f"expected an integer in 1..{MAX_WINDOW}, got {value!r}")
    return int(value)


def _check_threshold(name: str, value: float) -> np.float32:
    v = float(value)
    if not v >= 0 or v == float("inf"):
        raise CheckError(name, f"expected a finite threshold >= 0, got {value!r}")
    return np.float32(v)


def _window_offsets(window: int, subsample: int | None = None) -> np.ndarray:
    """Offsets along one axis of a k x k window, optionally sub-sampled to `subsample`
    evenly spaced positions (rounded half up; both window ends kept; s=1 keeps offset 0)."""
    first = -(window // 2)
    if subsample is None or subsample >= window:
        idx = np.arange(window)
    elif subsample == 1:
        idx = np.array([window // 2])
    else:
        i = np.arange(subsample)
        idx = (2 * i * (window - 1) + (subsample - 1)) // (2 * (subsample - 1))
    return (first + idx).astype(np.int64)


def _run_merge(dc, dv, inten, k, lam_i, lam_d, backend):
    out = np.empty_like(dc)
    valid_sum = cv2.integral((dc > 0).astype(np.uint8))  # (H+1, W+1) int32
    if backend == "cuda":
        return _cuda_launch(0, k * k, dc.shape, dc, dv, inten, valid_sum, k, lam_i, lam_d, out)
    _merge_cpu(dc, dv, inten, valid_sum, k, lam_i, lam_d, out)
    return out


def _run_support_median(depth, inten, offsets, lam_i, gate, backend):
    out = np.empty_like(depth)
    if backend == "cuda":
        return _cuda_launch(
            1, offsets.size**2, depth.shape, depth, inten, offsets, lam_i, gate, out
        )
    if offsets.size**2 <= MAX_NETWORK_INPUTS:  # 3-12x faster (speed page, "Depth filter, ...")
        threshold = lam_i if gate else np.float32(np.inf)
        support_median_rows(depth, inten, offsets, threshold, median_network(offsets.size**2), out)
        return out
    _support_median_cpu(depth, inten, offsets, lam_i, gate, out)
    return out


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


def merge_depth(
    depth_raw_m: np.ndarray,
    depth_volume_m: np.ndarray | None,
    intensity: np.ndarray,
    window: int = 20,
    intensity_threshold: float = 7.0,
    depth_threshold_m: float = 0.05,
    *,
    backend: str = "cpu",
) -> np.ndarray:
    """D' (eq. 1-3): fuse the sensor depth D_c with the volume depth D_v.

    depth_raw_m, depth_volume_m: (H, W) float metres, 0 or NaN = missing; depth_volume_m
    None = no volume (all missing). intensity: (H, W) grey levels 0..255.
    window: k of the hole-filling support; intensity_threshold: lambda_I (grey levels);
    depth_threshold_m: lambda_D (metres). Returns (H, W) float32 metres, 0 = still missing.
    See the module docstring for the exact case rules.
    """
    dc = _check_depth("depth_raw_m", depth_raw_m)
    if depth_volume_m is None:
        dv = np.zeros_like(dc)
    else:
        dv = _check_depth("depth_volume_m", depth_volume_m, dc.shape)
    inten = _check_intensity(intensity, dc.shape)
    k = _check_window("window", window)
    lam_i = _check_threshold("intensity_threshold", intensity_threshold)
    lam_d = _check_threshold("depth_threshold_m", depth_threshold_m)
    return _run_merge(dc, dv, inten, k, lam_i, lam_d, _check_backend(backend))


def joint_bilateral_median(
    depth_m: np.ndarray,
    intensity: np.ndarray,
    window: int = 8,
    intensity_threshold: float = 7.0,
    subsample: int = 5,
    *,
    backend: str = "cpu",
) -> np.ndarray:
    """D'' (eq. 4): lower median of depth over Omega_I(p) on a sub-sampled k x k window.

    The k offsets per axis are reduced to `subsample` evenly spaced ones (k=8, s=5:
    -4, -2, 0, 1, 3), giving s x s candidates; valid depth with |I(p) - I(q)| < lambda_I
    forms the support. Runs on every pixel, missing ones included; 0 where the support is
    empty. depth_m: (H, W) float metres, 0 or NaN = missing. Returns (H, W) float32.
    """
    depth = _check_depth("depth_m", depth_m)
    inten = _check_intensity(intensity, depth.shape)
    k = _check_window("window", window)
    s = _check_window("subsample", subsample)
    lam_i = _check_threshold("intensity_threshold", intensity_threshold)
    offsets = _window_offsets(k, s)
    return _run_support_median(depth, inten, offsets, lam_i, True, _check_backend(backend))


def median_depth(depth_m: np.ndarray, window: int = 2, *, backend: str = "cpu") -> np.ndarray:
    """D''' (eq. 5): lower median of the valid depth in the k x k window (no sub-sampling,
    no intensity gate). depth_m: (H, W) float metres, 0 or NaN = missing. Returns (H, W)
    float32, 0 where the window holds no valid depth."""
    depth = _check_depth("depth_m", depth_m)
    k = _check_window("window", window)
    offsets = _window_offsets(k)
    return _run_support_median(
        depth, depth, offsets, np.float32(0.0), False, _check_backend(backend)
    )


def backend_for_device(device: str) -> str:
    """The kernels' backend for an Open3D device name ("CUDA:0" -> "cuda", else "cpu")."""
    return "cuda" if device.startswith("CUDA") else "cpu"


def filter_depth(
    depth_raw_m: np.ndarray,
    depth_volume_m: np.ndarray | None,
    intensity: np.ndarray,
    params: FilterParams,
    *,
    backend: str = "cpu",
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The filter chain D' -> D'' -> D''' with the stage's parameters; a pass that is
    off (params.merge, params.smooth, params.denoise) passes its input on unchanged.

    Returns the final depth (H, W) float32 metres (0 = missing) and the intermediate
    passes {"merged": D', "smoothed": D''[, "denoised": D''']}.
    backend: "cpu" or "cuda" (`backend_for_device`; "cuda" without a usable GPU raises
    RuntimeError).
    """
    merged = _check_depth("depth_raw_m", depth_raw_m)
    if params.merge:
        merged = merge_depth(
            depth_raw_m,
            depth_volume_m,
            intensity,
            params.merge_window,
            params.merge_intensity_threshold,
            params.merge_depth_threshold_m,
            backend=backend,
        )
    smoothed = merged
    if params.smooth:
        smoothed = joint_bilateral_median(
            merged,
            intensity,
            params.smooth_window,
            params.smooth_intensity_threshold,
            params.smooth_subsample,
            backend=backend,
        )
    passes = {"merged": merged, "smoothed": smoothed}
    if not params.denoise:
        return smoothed, passes
    denoised = median_depth(smoothed, params.denoise_window, backend=backend)
    passes["denoised"] = denoised
    return denoised, passes


def normals_from_depth(
    depth_m: np.ndarray,
    camera: PinholeCamera,
    *,
    max_relative_jump: float = NORMAL_MAX_RELATIVE_JUMP,
    backend: str = "cpu",
) -> np.ndarray:
    """Unit normals (H, W, 3) float32 in the camera frame (OpenCV axes), facing the camera.

    Tangents are differences of unprojected neighbours: central where both neighbours along
    an axis exist, one-sided where only one does; a neighbour whose depth differs by more
    than `max_relative_jump` times the pixel's depth lies across a discontinuity and is not
    used. Pixels with missing depth or no usable neighbour along x or y get (0, 0, 0).
    depth_m: (H, W) float metres, 0 or NaN = missing, with the camera's width and height.
    """
    depth = _check_depth("depth_m", depth_m)
    if not isinstance(camera, PinholeCamera):
        raise ValueError(f"camera: expected a PinholeCamera, got {type(camera).__name__}")
    if depth.shape != (camera.height, camera.width):
        raise ValueError(
            f"depth_m: expected shape {(camera.height, camera.width)} "
            f"(camera height, width), got {depth.shape}"
        )
    jump = float(max_relative_jump)
    if not 0 < jump < float("inf"):
        raise ValueError(f"max_relative_jump: expected a finite value > 0, got {jump!r}")
    args = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), jump)
    out = np.empty(depth.shape + (3,), np.float32)
    if _check_backend(backend) == "cuda":
        return _cuda_launch(2, 0, depth.shape, depth, *args, out)
    _normals_cpu(depth, *args, out)
    return out


# --------------------------------------------------------------------------------------
# NumPy references (test oracles; slow, written for reading)
# --------------------------------------------------------------------------------------


def _lower_median_reference(values: np.ndarray) -> np.float32:
    return np.sort(values)[(values.size - 1) // 2]


def _window_slices(y: int, x: int, k: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    h, w = shape
    return (
        slice(max(y - k // 2, 0), min(y - k // 2 + k, h)),
        slice(max(x - k // 2, 0), min(x - k // 2 + k, w)),
    )


def _merge_depth_reference(
    dc, dv, inten, window=20, intensity_threshold=7.0, depth_threshold_m=0.05
):
    """D' pixel by pixel, written as eq. 1-3 (float32 comparisons as the kernels)."""
    dc = np.nan_to_num(np.asarray(dc, np.float32), nan=0.0)
    dv = np.nan_to_num(np.asarray(dv, np.float32), nan=0.0)
    inten = np.asarray(inten, np.float32)
    lam_i, lam_d = np.float32(intensity_threshold), np.float32(depth_threshold_m)
    out = np.zeros_like(dc)
    for y in range(dc.shape[0]):
        for x in range(dc.shape[1]):
            if dc[y, x] > 0:
                agrees = dv[y, x] > 0 and abs(dc[y, x] - dv[y, x]) < lam_d
                out[y, x] = dv[y, x] if agrees else dc[y, x]
                continue
            win = _window_slices(y, x, window, dc.shape)
            c, v, i = dc[win], dv[win], inten[win]
            omega_i = (c > 0) & (np.abs(inten[y, x] - i) < lam_i)  # eq. 1
            omega_d = omega_i & (v > 0) & (np.abs(c - v) < lam_d)  # eq. 2
            if omega_i.any():
                if dv[y, x] > 0 and omega_d.sum() >= omega_i.sum() / 2:
                    out[y, x] = dv[y, x]
                else:
                    out[y, x] = _lower_median_reference(c[omega_i])
            else:
                out[y, x] = dv[y, x]  # 0 when the volume has nothing either
    return out


def _support_median_reference(depth, inten, offsets, lam_i, gate):
    depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0)
    h, w = depth.shape
    out = np.zeros_like(depth)
    for y in range(h):
        for x in range(w):
            rows = y + offsets[(y + offsets >= 0) & (y + offsets < h)]
            cols = x + offsets[(x + offsets >= 0) & (x + offsets < w)]
            d = depth[np.ix_(rows, cols)]
            keep = d > 0
            if gate:
                keep &= np.abs(inten[y, x] - inten[np.ix_(rows, cols)]) < np.float32(lam_i)
            if keep.any():
                out[y, x] = _lower_median_reference(d[keep])
    return out


def _joint_bilateral_median_reference(depth, inten, window=8, intensity_threshold=7.0, subsample=5):
    """D'' (eq. 4) pixel by pixel."""
    return _support_median_reference(
        depth,
        np.asarray(inten, np.float32),
        _window_offsets(window, subsample),
        intensity_threshold,
        True,
    )


def _median_depth_reference(depth, window=2):
    """D''' (eq. 5) pixel by pixel."""
    return _support_median_reference(depth, None, _window_offsets(window), 0.0, False)


def _normals_from_depth_reference(depth, camera, max_relative_jump=NORMAL_MAX_RELATIVE_JUMP):
    """Normals pixel by pixel from camera.unproject (float64)."""
    depth = np.nan_to_num(np.asarray(depth, np.float64), nan=0.0)
    h, w = depth.shape
    u = (np.arange(w) - camera.cx) / camera.fx
    v = (np.arange(h) - camera.cy) / camera.fy
    points = np.stack([depth * u[None, :], depth * v[:, None], depth], axis=-1)
    out = np.zeros((h, w, 3), np.float32)

    def usable(y, x, qy, qx):
        return (
            0 <= qy < h
            and 0 <= qx < w
            and depth[qy, qx] > 0
            and abs(depth[qy, qx] - depth[y, x]) <= max_relative_jump * depth[y, x]
        )

    for y in range(h):
        for x in range(w):
            if not depth[y, x] > 0:
                continue
            tangents = []
            for dy, dx in ((0, 1), (1, 0)):
                ahead = usable(y, x, y + dy, x + dx)
                behind = usable(y, x, y - dy, x - dx)
                if not (ahead or behind):
                    break
                a = points[y + dy, x + dx] if ahead else points[y, x]
                b = points[y - dy, x - dx] if behind else points[y, x]
                tangents.append(a - b)
            if len(tangents) < 2:
                continue
            n = np.cross(tangents[0], tangents[1])
            norm = np.linalg.norm(n)
            if norm > 0:
                out[y, x] = -n / norm if n @ points[y, x] > 0 else n / norm
    return out
