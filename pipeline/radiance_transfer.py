"""Image-space radiance transfer into per-pixel SH (section 5.1, eq. 6-9 of seeds/000).

For a visible surface point x with normal n, N jittered directions w_j are tested with
SSDO: the sample y_j = x + r_j w_j is projected into the main geometry buffer (the
filtered depth G_r) and into the auxiliary orthographic buffers; where a buffer's surface
s_j lies in front of y_j the direction is (partly) blocked, with the continuous visibility

    t_j = (s_j - x) / |s_j - x|                                  (eq. 7)
    K(x, w_j) = min(chi, 1 - t_j . w_j) / chi                     (eq. 8)
    chi = cos(median angle between Delaunay neighbours / 2)       (eq. 9)

and the transfer vector is T_z(x) = sum_j K_j max(0, w_j . n) Y_z(w_j) 4 pi / N (eq. 6
without the albedo, which the light estimate absorbs). Geometry is in the CAMERA frame;
the SH basis is evaluated on the directions rotated into the WORLD frame, so T (and the
light solved from it) is in world coordinates. Random sample distances r_j are drawn per
position in a 2 x 2 pixel block (interleaved sampling), seeded from the config.

The per-pixel logic is written once (`register_jitable`) and driven by a parallel CPU
loop, here. It evaluates one scene, or two at once (`transfer_pair_at_pixels`: the
renderer's real pixels without and with the virtual objects share each sample's
projections and every surface the two scenes have in common). The rest lives beside it
and is re-exported from this module:
`transfer_sampling.py` (the directions, radii and chi), `transfer_types.py` (the kernels'
packed inputs, their result and the depth-test constants), `transfer_upsampling.py` (grid to
pixels), `transfer_quadrature.py` (the exact unoccluded part) and `transfer_oracle.py` (the
plain NumPy version, `transfer_reference`, kept as the test oracle).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from numba.extending import register_jitable

from arlight.core.camera import PinholeCamera
from arlight.core.checks import check_image
from arlight.pipeline import sh
from arlight.pipeline.config import TransferParams
from arlight.pipeline.horizon import SupportPlane
from arlight.pipeline.transfer_oracle import (
    _occlusion_reference,
    _visibility_reference,
    transfer_reference,
)
from arlight.pipeline.transfer_quadrature import (
    QUADRATURE_TABLE_SIZE,
    quadrature_error_table,
    unoccluded_quadrature_error,
    with_exact_unoccluded,
)
from arlight.pipeline.transfer_sampling import (
    SamplingPattern,
    jittered_directions,
    make_sampling_pattern,
    visibility_ramp,
    visibility_threshold,
)
from arlight.pipeline.transfer_types import (
    BIAS_ABS_M,
    BIAS_REL,
    HORIZON_BELOW_M,
    AuxBufferArrays,
    TransferResult,
)
from arlight.pipeline.transfer_upsampling import (
    REMAP_MAX_CHANNELS,
    TransferSamples,
    interpolated_samples,
    random_pixels,
    transfer_samples,
    upsample_transfer,
)

# the transfer's public names, wherever they are defined (callers import them from here);
# the two private oracle functions for the tests that compare them with the kernels
__all__ = [
    "BIAS_ABS_M",
    "BIAS_REL",
    "HORIZON_BELOW_M",
    "QUADRATURE_TABLE_SIZE",
    "REMAP_MAX_CHANNELS",
    "AuxBufferArrays",
    "SamplingPattern",
    "TransferResult",
    "TransferSamples",
    "_occlusion_reference",
    "_visibility_reference",
    "compute_transfer",
    "interpolated_samples",
    "jittered_directions",
    "make_sampling_pattern",
    "plane_arrays",
    "quadrature_error_table",
    "random_pixels",
    "transfer_at_pixels",
    "transfer_pair_at_pixels",
    "transfer_reference",
    "transfer_samples",
    "unoccluded_quadrature_error",
    "upsample_transfer",
    "visibility_ramp",
    "visibility_threshold",
    "with_exact_unoccluded",
]


_LIST_CHUNK = 64  # listed pixels a worker takes at a time


@register_jitable
def _occlusion(px, py, pz, yx, yy, yz, sx, sy, sz, wx, wy, wz, chi):
    """K of eq. 7-8 for an occluding surface point s seen from x towards direction w."""
    tx, ty, tz = sx - px, sy - py, sz - pz
    norm = math.sqrt(tx * tx + ty * ty + tz * tz)
    if norm < 1e-9:
        return 1.0
    cos_tw = (tx * wx + ty * wy + tz * wz) / norm
    return min(chi, 1.0 - cos_tw) / chi if chi > 0.0 else 1.0


@register_jitable(inline="always")
def _main_occlusion(sample, u, v, sz, fx, fy, cx, cy, bias, test):
    """K of the main buffer's surface at pixel (u, v), depth sz, for sample = (x, y, w) (9
    floats: the point, the sample, the direction) of x towards w; 1 where that surface is
    not in front of y. bias: metres; test: (chi, bias_abs, bias_rel, thickness)."""
    px, py, pz, yx, yy, yz, wx, wy, wz = sample
    chi, thickness = test[0], test[3]
    if sz > 0.0 and sz < yz - bias and sz > yz - thickness:
        sx = (u - cx) / fx * sz
        sy = (v - cy) / fy * sz
        return _occlusion(px, py, pz, yx, yy, yz, sx, sy, sz, wx, wy, wz, chi)
    return 1.0


@register_jitable(inline="always")
def _aux_occlusion(sample, m, ub, vb, half, pix, bz, sd, test):
    """K of an auxiliary buffer's surface at texel (ub, vb), depth sd along its +z, for the
    sample (as `_main_occlusion`; bz: y's depth in the buffer); m (3, 4): buffer_from_cam;
    pix: metres per texel; 1 where that surface is not in front of y."""
    px, py, pz, yx, yy, yz, wx, wy, wz = sample
    chi, bias_abs, bias_rel, thickness = test
    if sd > 0.0 and sd < bz - (bias_abs + bias_rel * 0.5 * sd) and sd > bz - thickness:
        # surface point in the buffer frame -> camera frame (inverse of a rigid map)
        qx = (ub - half) * pix - m[0, 3]
        qy = (vb - half) * pix - m[1, 3]
        qz = sd - m[2, 3]
        sx = m[0, 0] * qx + m[1, 0] * qy + m[2, 0] * qz
        sy = m[0, 1] * qx + m[1, 1] * qy + m[2, 1] * qz
        sz = m[0, 2] * qx + m[1, 2] * qy + m[2, 2] * qz
        return _occlusion(px, py, pz, yx, yy, yz, sx, sy, sz, wx, wy, wz, chi)
    return 1.0


@register_jitable(inline="always")
def _visibility(
    px,
    py,
    pz,
    wx,
    wy,
    wz,
    radius,
    depth,
    fx,
    fy,
    cx,
    cy,
    aux_depth,
    aux_from_cam,
    aux_pix,
    aux_point,
    aux_dir,
    j,
    chi,
    bias_abs,
    bias_rel,
    thickness,
):
    """Continuous visibility K in [0, 1] of one sample y = x + radius * w, against each
    configuration's buffers: depth (S, H, W), aux_depth (S, B, R, R), S = 1 or 2 (the
    second: the same scene with the virtual objects in). aux_point (B, 3): x in each
    buffer as (texel u, texel v, depth); aux_dir (B, N, 3): the N directions there (texels,
    texels, metres), w = direction j, so that y's texel and depth in buffer b are
    aux_point[b] + radius * aux_dir[b, j]. Returns (K of the first, K of the second or 1);
    a surface both configurations share is tested once."""
    yx, yy, yz = px + radius * wx, py + radius * wy, pz + radius * wz
    sample = (px, py, pz, yx, yy, yz, wx, wy, wz)
    test = (chi, bias_abs, bias_rel, thickness)
    k0 = 1.0
    k1 = 1.0
    two = depth.shape[0] > 1
    h, w = depth.shape[1], depth.shape[2]
    if yz > 1e-6:
        u = int(round(fx * yx / yz + cx))
        v = int(round(fy * yy / yz + cy))
        if 0 <= u < w and 0 <= v < h:
            bias = bias_abs + bias_rel * yz
            sz = depth[0, v, u]
            o = _main_occlusion(sample, u, v, sz, fx, fy, cx, cy, bias, test)
            k0 = min(k0, o)
            if two:
                if depth[1, v, u] != sz:  # else the surface both scenes share: tested once
                    o = _main_occlusion(sample, u, v, depth[1, v, u], fx, fy, cx, cy, bias, test)
                k1 = min(k1, o)
    r = aux_depth.shape[2]
    half = 0.5 * (r - 1)
    for b in range(aux_depth.shape[1]):  # (no view of aux_from_cam[b] here: 12 % slower)
        ub = int(round(aux_point[b, 0] + radius * aux_dir[b, j, 0]))
        vb = int(round(aux_point[b, 1] + radius * aux_dir[b, j, 1]))
        bz = aux_point[b, 2] + radius * aux_dir[b, j, 2]
        if 0 <= ub < r and 0 <= vb < r:
            sd = aux_depth[0, b, vb, ub]
            o = _aux_occlusion(sample, aux_from_cam[b], ub, vb, half, aux_pix[b], bz, sd, test)
            k0 = min(k0, o)
            if two:
                sd1 = aux_depth[1, b, vb, ub]
                if sd1 != sd:
                    o = _aux_occlusion(
                        sample, aux_from_cam[b], ub, vb, half, aux_pix[b], bz, sd1, test
                    )
                k1 = min(k1, o)
    return k0, k1


@register_jitable
def _ground_pixel(px, py, pz, wx, wy, wz, t, depth, fx, fy, cx, cy):
    """(u, v) of the ground where the ray x + t w meets it, when the camera sees that spot
    (in the image, depth within 5 %), else (-1, -1)."""
    hz = pz + t * wz
    if hz > 1e-6:
        u = int(round(fx * (px + t * wx) / hz + cx))
        v = int(round(fy * (py + t * wy) / hz + cy))
        if 0 <= u < depth.shape[1] and 0 <= v < depth.shape[0]:
            d = depth[v, u]
            if d > 0.0 and abs(d - hz) < 0.05 * hz:
                return u, v
    return -1, -1


@register_jitable
def _transfer_pixel(
    ui,
    vi,
    points,
    normals,
    depth,
    fx,
    fy,
    cx,
    cy,
    dirs,
    ysh,
    radii,
    aux_depth,
    aux_from_cam,
    aux_pix,
    aux_dir,
    chi,
    bias_abs,
    bias_rel,
    thickness,
    use_visibility,
    radiance,
    plane,
    ground,
    out,
    bounce,
    aux_point,
):
    """Fill out (S, C) with the SH transfer vector of pixel (ui, vi) and bounce (S, B) with
    sum_j (1 - K_j) max(0, w_j . n) I(s_j) 4 pi / N, the one-bounce light from the occluders,
    I(s_j) the radiance image where the blocking sample projects (no bounce when radiance is
    not image-sized, e.g. (S, 1, 1, B)), for each of S = 1 or 2 configurations of the
    buffers: depth (S, H, W), aux_depth (S, B', R, R), radiance (S, H, W, B), ground (S, B)
    (the renderer's real scene, and the same with the virtual objects in, at a real pixel:
    its point and normal, from points and normals, are the same in both). Returns False
    where the pixel has no geometry (out and bounce zero).

    plane (4,): (up, offset) of the support plane, camera frame, or zeros (none): for a
    point above it, a direction below its horizon meets the ground, so it adds the ground's
    radiance (where the ray hits it, if seen there, else `ground`) to the bounce and
    nothing to the transfer. aux_dir (B', N, 3): the directions in each auxiliary buffer
    (`_aux_directions`); aux_point: (B', 3) scratch.
    """
    out[:] = 0.0
    bounce[:] = 0.0
    pz = points[vi, ui, 2]
    nx, ny, nz = normals[vi, ui, 0], normals[vi, ui, 1], normals[vi, ui, 2]
    if not (pz > 0.0) or (nx == 0.0 and ny == 0.0 and nz == 0.0):
        return False
    px, py = points[vi, ui, 0], points[vi, ui, 1]
    h, w = depth.shape[1], depth.shape[2]
    with_bounce = radiance.shape[1] == h and radiance.shape[2] == w
    scenes = depth.shape[0]
    nb = bounce.shape[1]
    ux, uy, uz = plane[0], plane[1], plane[2]
    height = ux * px + uy * py + uz * pz + plane[3]
    # points clearly under the plane (a floor seen past a table's edge) are not shadowed by it
    use_plane = (ux != 0.0 or uy != 0.0 or uz != 0.0) and height > -HORIZON_BELOW_M
    half = 0.5 * (aux_depth.shape[2] - 1)
    for b in range(aux_depth.shape[1]):  # x in each buffer: texel u, v and depth
        m = aux_from_cam[b]
        aux_point[b, 0] = (m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]) / aux_pix[b]
        aux_point[b, 1] = (m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]) / aux_pix[b]
        aux_point[b, 0] += half
        aux_point[b, 1] += half
        aux_point[b, 2] = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
    n_dirs = dirs.shape[0]
    weight = 4.0 * math.pi / n_dirs
    steps = radii.shape[3]
    for j in range(n_dirs):
        wx, wy, wz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        cos_n = wx * nx + wy * ny + wz * nz
        if cos_n <= 0.0:
            continue
        k0 = 1.0
        k1 = 1.0
        blocker0 = 0.0
        blocker1 = 0.0
        if use_visibility:
            for s in range(steps):
                radius = radii[vi % 2, ui % 2, j, s]
                ks0, ks1 = _visibility(
                    px,
                    py,
                    pz,
                    wx,
                    wy,
                    wz,
                    radius,
                    depth,
                    fx,
                    fy,
                    cx,
                    cy,
                    aux_depth,
                    aux_from_cam,
                    aux_pix,
                    aux_point,
                    aux_dir,
                    j,
                    chi,
                    bias_abs,
                    bias_rel,
                    thickness,
                )
                if ks0 < k0:
                    k0 = ks0
                    blocker0 = radius
                if ks1 < k1:
                    k1 = ks1
                    blocker1 = radius
        cos_up = wx * ux + wy * uy + wz * uz
        plane_part = use_plane and cos_up < 0.0
        for c in range(scenes):
            k = k0 if c == 0 else k1
            blocker = blocker0 if c == 0 else blocker1
            f = k * cos_n * weight
            if plane_part:
                if with_bounce and f > 0.0:
                    gu, gv = _ground_pixel(
                        px, py, pz, wx, wy, wz, max(height, 0.0) / -cos_up, depth[c], fx, fy, cx, cy
                    )
                    for i in range(nb):
                        bounce[c, i] += f * (radiance[c, gv, gu, i] if gu >= 0 else ground[c, i])
            elif f > 0.0:
                for i in range(out.shape[1]):
                    out[c, i] += f * ysh[j, i]
            if with_bounce and k < 1.0:
                yz = pz + blocker * wz
                if yz > 1e-6:
                    u = int(round(fx * (px + blocker * wx) / yz + cx))
                    v = int(round(fy * (py + blocker * wy) / yz + cy))
                    if 0 <= u < w and 0 <= v < h:
                        for i in range(nb):
                            bounce[c, i] += (1.0 - k) * cos_n * weight * radiance[c, v, u, i]
    return True


@numba.njit(parallel=True, cache=True)
def _transfer_cpu(
    points,
    normals,
    depth,
    fx,
    fy,
    cx,
    cy,
    dirs,
    ysh,
    radii,
    aux_depth,
    aux_from_cam,
    aux_pix,
    aux_dir,
    chi,
    bias_abs,
    bias_rel,
    thickness,
    use_visibility,
    radiance,
    plane,
    ground,
    step,
    transfer,
    bounce,
    valid,
):
    hs, ws = valid.shape
    h, w = depth.shape[1], depth.shape[2]
    for i in numba.prange(hs):
        vi = min(i * step + step // 2, h - 1)
        aux_point = np.empty((aux_depth.shape[1], 3))
        for jj in range(ws):
            ui = min(jj * step + step // 2, w - 1)
            valid[i, jj] = _transfer_pixel(
                ui,
                vi,
                points,
                normals,
                depth,
                fx,
                fy,
                cx,
                cy,
                dirs,
                ysh,
                radii,
                aux_depth,
                aux_from_cam,
                aux_pix,
                aux_dir,
                chi,
                bias_abs,
                bias_rel,
                thickness,
                use_visibility,
                radiance,
                plane,
                ground,
                transfer[i, jj],
                bounce[i, jj],
                aux_point,
            )


@numba.njit(parallel=True, cache=True)
def _transfer_list_cpu(
    points,
    normals,
    depth,
    fx,
    fy,
    cx,
    cy,
    dirs,
    ysh,
    radii,
    aux_depth,
    aux_from_cam,
    aux_pix,
    aux_dir,
    chi,
    bias_abs,
    bias_rel,
    thickness,
    use_visibility,
    radiance,
    plane,
    ground,
    us,
    vs,
    transfer,
    bounce,
    valid,
):
    n = us.shape[0]
    chunks = (n + _LIST_CHUNK - 1) // _LIST_CHUNK
    for chunk in numba.prange(chunks):
        aux_point = np.empty((aux_depth.shape[1], 3))  # a scratch per chunk, not per pixel
        for p in range(chunk * _LIST_CHUNK, min(n, (chunk + 1) * _LIST_CHUNK)):
            valid[p] = _transfer_pixel(
                us[p],
                vs[p],
                points,
                normals,
                depth,
                fx,
                fy,
                cx,
                cy,
                dirs,
                ysh,
                radii,
                aux_depth,
                aux_from_cam,
                aux_pix,
                aux_dir,
                chi,
                bias_abs,
                bias_rel,
                thickness,
                use_visibility,
                radiance,
                plane,
                ground,
                transfer[p],
                bounce[p],
                aux_point,
            )


def compute_transfer(
    points_cam: np.ndarray,
    normals_cam: np.ndarray,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    pattern: SamplingPattern,
    aux: AuxBufferArrays | None,
    params: TransferParams,
    luminance: np.ndarray | None = None,
    plane: SupportPlane | None = None,
) -> TransferResult:
    """SH radiance transfer for every `params.rt_subsample`-th pixel (section 5.1, eq. 6-9).

    points_cam: (H, W, 3) float32 camera-frame points of the filtered depth (z = 0 missing);
    normals_cam: (H, W, 3) unit normals, camera frame, zeros where unknown;
    luminance: optional (H, W) linear image luminance: with it, the one-bounce light of
    the occluders is gathered as well (`TransferResult.bounce`, as in SSDO);
    plane: optional support plane (camera frame): directions below its horizon see the
    ground, never the distant light (their light, the ground's luminance, goes to bounce).
    """
    h, w = points_cam.shape[:2]
    step = params.rt_subsample
    hs, ws = (h + step - 1) // step, (w + step - 1) // step
    if luminance is not None:  # a public entry: the one image not made from points_cam
        check_image(luminance, "luminance", size=(w, h))
        luminance = np.asarray(luminance)[..., None]
    k = _KernelInputs.make(
        points_cam, normals_cam, world_from_cam, pattern, aux, params, luminance, plane
    )
    transfer = np.zeros((hs, ws, 1, k.ysh.shape[1]), np.float64)
    valid = np.zeros((hs, ws), np.bool_)
    bounce = np.zeros((hs, ws, 1, 1), np.float64)
    _transfer_cpu(*k.args(camera, params, pattern), step, transfer, bounce, valid)
    transfer, bounce = transfer[:, :, 0], bounce[:, :, 0]
    u = np.minimum(np.arange(ws) * step + step // 2, w - 1)
    v = np.minimum(np.arange(hs) * step + step // 2, h - 1)
    return TransferResult(
        transfer.astype(np.float32),
        valid,
        u,
        v,
        bounce[..., 0].astype(np.float32) if luminance is not None else None,
    )


def transfer_at_pixels(
    points_cam: np.ndarray,
    normals_cam: np.ndarray,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    pattern: SamplingPattern,
    aux: AuxBufferArrays | None,
    params: TransferParams,
    pixels_u: np.ndarray,
    pixels_v: np.ndarray,
    radiance: np.ndarray | None = None,
    plane: SupportPlane | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The transfer of :func:`compute_transfer` at the listed pixels only (the renderer's
    region around the virtual objects): (transfer (K, C) float64, bounce (K, B) float64,
    valid (K,) bool). radiance: optional (H, W, B) linear image whose light the occluders
    bounce (B channels, e.g. RGB); without it bounce is (K, 0)."""
    k = _KernelInputs.make(
        points_cam, normals_cam, world_from_cam, pattern, aux, params, radiance, plane
    )
    transfer, bounce, valid = _listed(k, None, camera, params, pattern, pixels_u, pixels_v)
    return transfer[:, 0], bounce[:, 0], valid


def transfer_pair_at_pixels(
    points_cam: np.ndarray,
    points_second: np.ndarray,
    normals_cam: np.ndarray,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    pattern: SamplingPattern,
    aux: AuxBufferArrays | None,
    aux_second: AuxBufferArrays | None,
    params: TransferParams,
    pixels_u: np.ndarray,
    pixels_v: np.ndarray,
    radiance: np.ndarray | None = None,
    radiance_second: np.ndarray | None = None,
    plane: SupportPlane | None = None,
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], np.ndarray]:
    """`transfer_at_pixels` of two scenes at once, at pixels where both have the same
    point and normal (the renderer's real pixels, without and with the virtual objects):
    the second scene's depth from points_second (H, W, 3), its own auxiliary buffers (the
    same count, size and frames as `aux`) and radiance image (as `radiance`). Each sample's
    projections are computed once and a surface both scenes share is tested once.
    Returns ((transfer, bounce) of the first, (transfer, bounce) of the second, valid):
    the same arrays as two `transfer_at_pixels` calls."""
    first = _KernelInputs.make(
        points_cam, normals_cam, world_from_cam, pattern, aux, params, radiance, plane
    )
    second = _KernelInputs.make(
        points_second,
        normals_cam,
        world_from_cam,
        pattern,
        aux_second,
        params,
        radiance_second,
        plane,
    )
    transfer, bounce, valid = _listed(first, second, camera, params, pattern, pixels_u, pixels_v)
    return (transfer[:, 0], bounce[:, 0]), (transfer[:, 1], bounce[:, 1]), valid


def _listed(
    first: _KernelInputs,
    second: _KernelInputs | None,
    camera: PinholeCamera,
    params: TransferParams,
    pattern: SamplingPattern,
    pixels_u: np.ndarray,
    pixels_v: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The list kernel over one or two scenes: transfer (K, S, C), bounce (K, S, B)
    (B = 0 without radiance), valid (K,)."""
    us = np.ascontiguousarray(pixels_u, dtype=np.int64)
    vs = np.ascontiguousarray(pixels_v, dtype=np.int64)
    scenes = 1 if second is None else 2
    channels = first.radiance.shape[2] if first.with_radiance else 0
    transfer = np.zeros((len(us), scenes, first.ysh.shape[1]), np.float64)
    bounce = np.zeros((len(us), scenes, max(channels, 1)), np.float64)
    valid = np.zeros(len(us), np.bool_)
    if len(us):
        args = first.args(camera, params, pattern, second)
        _transfer_list_cpu(*args, us, vs, transfer, bounce, valid)
    return transfer, bounce[:, :, :channels], valid


@dataclass
class _KernelInputs:
    """The arrays the transfer kernels take, contiguous and typed once."""

    points: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    ysh: np.ndarray
    aux: AuxBufferArrays
    radiance: np.ndarray
    plane: np.ndarray
    ground: np.ndarray
    with_radiance: bool

    @classmethod
    def make(
        cls, points_cam, normals_cam, world_from_cam, pattern, aux, params, radiance, plane
    ) -> _KernelInputs:
        dirs_world = pattern.directions @ np.asarray(world_from_cam, np.float64)[:3, :3].T
        points = np.ascontiguousarray(points_cam, dtype=np.float32)
        rad = (
            np.zeros((1, 1, 1), np.float32)
            if radiance is None
            else np.ascontiguousarray(radiance, dtype=np.float32)
        )
        plane_arr, ground = plane_arrays(plane, rad if radiance is not None else None)
        return cls(
            points,
            np.ascontiguousarray(normals_cam, dtype=np.float32),
            np.ascontiguousarray(points[..., 2]),
            sh.sh_basis(dirs_world, params.sh_bands),
            aux if aux is not None else AuxBufferArrays.empty(),
            rad,
            plane_arr,
            np.broadcast_to(np.asarray(ground, np.float64), (rad.shape[2],)).copy(),
            radiance is not None,
        )

    def args(
        self,
        camera: PinholeCamera,
        params: TransferParams,
        pattern: SamplingPattern,
        second: _KernelInputs | None = None,
    ) -> tuple:
        """The kernels' arguments; with `second`, its depth, auxiliary depth, radiance and
        ground stacked after this one's (the kernels' two scenes)."""

        def stacked(get: Callable[[_KernelInputs], np.ndarray]) -> np.ndarray:
            """(S, ...) of one array per scene; a view of this one's alone."""
            mine = get(self)
            return mine[None] if second is None else np.stack([mine, get(second)])

        return (
            self.points,
            self.normals,
            stacked(lambda k: k.depth),
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            pattern.directions,
            self.ysh,
            pattern.radii,
            stacked(lambda k: k.aux.depth),
            self.aux.buffer_from_cam,
            self.aux.pixel_size,
            _aux_directions(self.aux, pattern.directions),
            visibility_ramp(pattern, params),
            BIAS_ABS_M,
            BIAS_REL,
            params.rt_thickness_m,
            params.visibility,
            stacked(lambda k: k.radiance),
            self.plane,
            stacked(lambda k: k.ground),
        )


def _aux_directions(aux: AuxBufferArrays, directions: np.ndarray) -> np.ndarray:
    """(B, N, 3) float64: the N camera-frame unit directions in each auxiliary buffer, as
    texels along its u and v and metres along its depth (the kernels step a sample's texel
    as x's texel + radius * this, with no projection per sample)."""
    rotated = np.einsum("bij,nj->bni", aux.buffer_from_cam[:, :, :3], directions)
    scale = np.ones((len(aux.pixel_size), 1, 3))
    scale[:, 0, :2] = aux.pixel_size[:, None]
    return np.ascontiguousarray(rotated / scale)


def plane_arrays(
    plane: SupportPlane | None, luminance: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | float]:
    """(up, offset) as a (4,) array (zeros: no plane) and the ground's median luminance:
    a float for an (H, W) image, per channel (B,) for an (H, W, B) one; 0 without either."""
    if plane is None:
        return np.zeros(4), 0.0
    ground = 0.0
    if luminance is not None and np.any(plane.on_plane):
        values = np.median(luminance[plane.on_plane], axis=0)
        ground = float(values) if np.ndim(values) == 0 else values.astype(np.float64)
    return np.array([*plane.up, plane.offset], dtype=np.float64), ground
