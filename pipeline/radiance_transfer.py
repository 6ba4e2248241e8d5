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
loop; a plain NumPy version (`transfer_reference`) is kept as the test oracle.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numba.extending import register_jitable
from scipy.spatial import ConvexHull

from arlight.checks import check_image
from arlight.pipeline import sh
from arlight.pipeline.camera import PinholeCamera
from arlight.pipeline.config import TransferParams, VisibilityRamp
from arlight.pipeline.horizon import SupportPlane


@dataclass(frozen=True)
class SamplingPattern:
    """Directions (N, 3) unit, camera frame; radii (2, 2, N, steps) metres; chi of eq. 9."""

    directions: np.ndarray
    radii: np.ndarray
    chi: float


def jittered_directions(n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` unit directions: a Fibonacci lattice with each point jittered within its cell."""
    base = sh.fibonacci_sphere(n)
    cell = math.sqrt(4.0 * math.pi / n)  # typical neighbour spacing, radians
    jitter = rng.normal(scale=0.25 * cell, size=(n, 3))
    jitter -= (jitter * base).sum(axis=1, keepdims=True) * base  # tangent to the sphere
    d = base + jitter
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def unoccluded_quadrature_error(
    normals_world: np.ndarray, directions_world: np.ndarray, bands: int
) -> np.ndarray:
    """(K, C): the exact clamped-cosine transfer of unit normals (K, 3), A_l Y_lm(n)
    (Ramamoorthi and Hanrahan 2001), minus the sampling pattern's estimate of it,
    sum_j max(0, n . w_j) Y(w_j) 4 pi / N, both world frame.

    Added to an SSDO transfer it is a control variate: the unoccluded part becomes exact and
    only the blocked directions keep the N-direction sampling error (which, with one
    direction set for every pixel, is a bias shared by a whole surface, not noise)."""
    n = np.asarray(normals_world, np.float64).reshape(-1, 3)
    dirs = np.asarray(directions_world, np.float64)
    # the (K, N) cosines in float32 (half the time; the sum is then good to ~1e-6)
    cos = np.maximum(n.astype(np.float32) @ dirs.T.astype(np.float32), 0.0)
    estimate = cos @ (sh.sh_basis(dirs, bands) * (4.0 * math.pi / len(dirs))).astype(np.float32)
    per_coeff = np.repeat(sh.lambert_band_factors(bands), [2 * l + 1 for l in range(bands)])
    return sh.sh_basis(n, bands) * per_coeff - estimate


def visibility_threshold(directions: np.ndarray) -> float:
    """chi of eq. 9: cos of half the median angle between neighbours of the spherical
    Delaunay triangulation (the convex hull of points on the unit sphere)."""
    hull = ConvexHull(directions)
    edges = set()
    for a, b, c in hull.simplices:
        for i, j in ((a, b), (b, c), (a, c)):
            edges.add((min(i, j), max(i, j)))
    idx = np.array(sorted(edges))
    cosines = np.clip((directions[idx[:, 0]] * directions[idx[:, 1]]).sum(axis=1), -1.0, 1.0)
    return float(math.cos(np.median(np.arccos(cosines)) / 2.0))


def make_sampling_pattern(params: TransferParams, seed: int = 0) -> SamplingPattern:
    """The N jittered directions, the sample radii and chi (eq. 9), seeded by `seed`."""
    rng = np.random.default_rng(seed)
    dirs = jittered_directions(params.rt_directions, rng)
    steps = params.rt_steps
    # one random distance per direction and 2x2 block position; with several steps per
    # direction the distances are stratified in (0, radius]
    u = rng.random((2, 2, params.rt_directions, steps))
    radii = (np.arange(steps) + u) / steps * params.rt_radius_m
    return SamplingPattern(dirs, radii.astype(np.float64), visibility_threshold(dirs))


def visibility_ramp(pattern: SamplingPattern, params: TransferParams) -> float:
    """The threshold c of K = min(c, 1 - t.w) / c: chi as printed in eq. 8 ("paper"), or
    1 - chi so K ramps over half the neighbour angle ("half")."""
    if params.rt_visibility_ramp is VisibilityRamp.PAPER:
        return pattern.chi
    return 1.0 - pattern.chi


@dataclass
class AuxBufferArrays:
    """Auxiliary orthographic buffers packed for the kernel.

    depth (B, R, R) float32 metres along each buffer's +z (0 = none); buffer_from_cam
    (B, 3, 4) rigid transforms; pixel_size (B,) metres per pixel.
    """

    depth: np.ndarray
    buffer_from_cam: np.ndarray
    pixel_size: np.ndarray

    @classmethod
    def empty(cls) -> AuxBufferArrays:
        return cls(np.zeros((0, 1, 1), np.float32), np.zeros((0, 3, 4)), np.zeros(0))

    @classmethod
    def from_buffers(cls, buffers, world_from_cam: np.ndarray) -> AuxBufferArrays:
        """From `OrthoBuffer`s (world_from_buffer, depth_m, pixel_size_m) of one size."""
        if not buffers:
            return cls.empty()
        depth = np.stack([b.depth_m for b in buffers]).astype(np.float32)
        b_from_c = np.stack(
            [(np.linalg.inv(b.world_from_buffer) @ world_from_cam)[:3] for b in buffers]
        )
        pix = np.array([b.pixel_size_m for b in buffers], dtype=np.float64)
        return cls(depth, b_from_c, pix)


@register_jitable
def _occlusion(px, py, pz, yx, yy, yz, sx, sy, sz, wx, wy, wz, chi):
    """K of eq. 7-8 for an occluding surface point s seen from x towards direction w."""
    tx, ty, tz = sx - px, sy - py, sz - pz
    norm = math.sqrt(tx * tx + ty * ty + tz * tz)
    if norm < 1e-9:
        return 1.0
    cos_tw = (tx * wx + ty * wy + tz * wz) / norm
    return min(chi, 1.0 - cos_tw) / chi if chi > 0.0 else 1.0


@register_jitable
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
    chi,
    bias_abs,
    bias_rel,
    thickness,
):
    """Continuous visibility K in [0, 1] of one sample y = x + radius * w."""
    yx, yy, yz = px + radius * wx, py + radius * wy, pz + radius * wz
    k = 1.0
    h, w = depth.shape
    if yz > 1e-6:
        u = int(round(fx * yx / yz + cx))
        v = int(round(fy * yy / yz + cy))
        if 0 <= u < w and 0 <= v < h:
            sz = depth[v, u]
            if sz > 0.0 and sz < yz - (bias_abs + bias_rel * yz) and sz > yz - thickness:
                sx = (u - cx) / fx * sz
                sy = (v - cy) / fy * sz
                k = min(k, _occlusion(px, py, pz, yx, yy, yz, sx, sy, sz, wx, wy, wz, chi))
    for b in range(aux_depth.shape[0]):
        m = aux_from_cam[b]
        bx = m[0, 0] * yx + m[0, 1] * yy + m[0, 2] * yz + m[0, 3]
        by = m[1, 0] * yx + m[1, 1] * yy + m[1, 2] * yz + m[1, 3]
        bz = m[2, 0] * yx + m[2, 1] * yy + m[2, 2] * yz + m[2, 3]
        r = aux_depth.shape[1]
        half = 0.5 * (r - 1)
        ub = int(round(bx / aux_pix[b] + half))
        vb = int(round(by / aux_pix[b] + half))
        if 0 <= ub < r and 0 <= vb < r:
            sd = aux_depth[b, vb, ub]
            if sd > 0.0 and sd < bz - (bias_abs + bias_rel * 0.5 * sd) and sd > bz - thickness:
                # surface point in the buffer frame -> camera frame (inverse of a rigid map)
                qx = (ub - half) * aux_pix[b] - m[0, 3]
                qy = (vb - half) * aux_pix[b] - m[1, 3]
                qz = sd - m[2, 3]
                sx = m[0, 0] * qx + m[1, 0] * qy + m[2, 0] * qz
                sy = m[0, 1] * qx + m[1, 1] * qy + m[2, 1] * qz
                sz = m[0, 2] * qx + m[1, 2] * qy + m[2, 2] * qz
                k = min(k, _occlusion(px, py, pz, yx, yy, yz, sx, sy, sz, wx, wy, wz, chi))
    return k


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
):
    """Fill out (C,) with the SH transfer vector of pixel (ui, vi) and bounce (B,) with
    sum_j (1 - K_j) max(0, w_j . n) I(s_j) 4 pi / N, the one-bounce light from the occluders,
    I(s_j) the radiance image (H, W, B) where the blocking sample projects (no bounce when
    radiance is not image-sized, e.g. (1, 1, B)). Returns False where the pixel has no
    geometry (out and bounce zero).

    plane (4,): (up, offset) of the support plane, camera frame, or zeros (none): for a
    point above it, a direction below its horizon meets the ground, so it adds the ground's
    radiance (where the ray hits it, if seen there, else `ground` (B,)) to the bounce and
    nothing to the transfer.
    """
    for c in range(out.shape[0]):
        out[c] = 0.0
    for c in range(bounce.shape[0]):
        bounce[c] = 0.0
    pz = points[vi, ui, 2]
    nx, ny, nz = normals[vi, ui, 0], normals[vi, ui, 1], normals[vi, ui, 2]
    if not (pz > 0.0) or (nx == 0.0 and ny == 0.0 and nz == 0.0):
        return False
    px, py = points[vi, ui, 0], points[vi, ui, 1]
    h, w = depth.shape
    with_bounce = radiance.shape[0] == h and radiance.shape[1] == w
    nb = bounce.shape[0]
    ux, uy, uz = plane[0], plane[1], plane[2]
    height = ux * px + uy * py + uz * pz + plane[3]
    # points clearly under the plane (a floor seen past a table's edge) are not shadowed by it
    use_plane = (ux != 0.0 or uy != 0.0 or uz != 0.0) and height > -HORIZON_BELOW_M
    n_dirs = dirs.shape[0]
    weight = 4.0 * math.pi / n_dirs
    steps = radii.shape[3]
    for j in range(n_dirs):
        wx, wy, wz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        cos_n = wx * nx + wy * ny + wz * nz
        if cos_n <= 0.0:
            continue
        k = 1.0
        blocker = 0.0
        if use_visibility:
            for s in range(steps):
                radius = radii[vi % 2, ui % 2, j, s]
                ks = _visibility(
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
                    chi,
                    bias_abs,
                    bias_rel,
                    thickness,
                )
                if ks < k:
                    k = ks
                    blocker = radius
        f = k * cos_n * weight
        cos_up = wx * ux + wy * uy + wz * uz
        if use_plane and cos_up < 0.0:
            if with_bounce and f > 0.0:
                gu, gv = _ground_pixel(
                    px, py, pz, wx, wy, wz, max(height, 0.0) / -cos_up, depth, fx, fy, cx, cy
                )
                for c in range(nb):
                    bounce[c] += f * (radiance[gv, gu, c] if gu >= 0 else ground[c])
        elif f > 0.0:
            for c in range(out.shape[0]):
                out[c] += f * ysh[j, c]
        if with_bounce and k < 1.0:
            yz = pz + blocker * wz
            if yz > 1e-6:
                u = int(round(fx * (px + blocker * wx) / yz + cx))
                v = int(round(fy * (py + blocker * wy) / yz + cy))
                if 0 <= u < w and 0 <= v < h:
                    for c in range(nb):
                        bounce[c] += (1.0 - k) * cos_n * weight * radiance[v, u, c]
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
    h, w = depth.shape
    for i in numba.prange(hs):
        vi = min(i * step + step // 2, h - 1)
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
    for p in numba.prange(us.shape[0]):
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
        )


@dataclass
class TransferResult:
    """Per-pixel SH transfer on the (sub-sampled) grid.

    transfer: (Hs, Ws, C) float32, world-frame SH; valid: (Hs, Ws) bool;
    pixel_u, pixel_v: (Ws,), (Hs,) full-resolution pixel coordinates of the grid;
    bounce: (Hs, Ws) float32 one-bounce light from the occluders (units of the luminance
    image given to compute_transfer, times steradians), or None.
    """

    transfer: np.ndarray
    valid: np.ndarray
    pixel_u: np.ndarray
    pixel_v: np.ndarray
    bounce: np.ndarray | None = None


# Depth-test bias: a sample counts as behind a surface only beyond this margin (metres,
# absolute + relative to depth), against sensor noise and quantisation.
BIAS_ABS_M = 0.01
BIAS_REL = 0.01
# points more than this below the support plane are not shadowed by it (metres)
HORIZON_BELOW_M = 0.05


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
    transfer = np.zeros((hs, ws, k.ysh.shape[1]), np.float64)
    valid = np.zeros((hs, ws), np.bool_)
    bounce = np.zeros((hs, ws, 1), np.float64)
    _transfer_cpu(*k.args(camera, params, pattern), step, transfer, bounce, valid)
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
    us = np.ascontiguousarray(pixels_u, dtype=np.int64)
    vs = np.ascontiguousarray(pixels_v, dtype=np.int64)
    k = _KernelInputs.make(
        points_cam, normals_cam, world_from_cam, pattern, aux, params, radiance, plane
    )
    channels = 0 if radiance is None else radiance.shape[2]
    transfer = np.zeros((len(us), k.ysh.shape[1]), np.float64)
    bounce = np.zeros((len(us), max(channels, 1)), np.float64)
    valid = np.zeros(len(us), np.bool_)
    if len(us):
        _transfer_list_cpu(*k.args(camera, params, pattern), us, vs, transfer, bounce, valid)
    return transfer, bounce[:, :channels], valid


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
        )

    def args(
        self, camera: PinholeCamera, params: TransferParams, pattern: SamplingPattern
    ) -> tuple:
        return (
            self.points,
            self.normals,
            self.depth,
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            pattern.directions,
            self.ysh,
            pattern.radii,
            self.aux.depth,
            self.aux.buffer_from_cam,
            self.aux.pixel_size,
            visibility_ramp(pattern, params),
            BIAS_ABS_M,
            BIAS_REL,
            params.rt_thickness_m,
            params.visibility,
            self.radiance,
            self.plane,
            self.ground,
        )


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


REMAP_MAX_CHANNELS = 128  # cv2 (5.0) reads an (H, W, C > 128) array as a 2-D image


def _remap_channels(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear cv2.remap of an (h, w, C) image for any C >= 1, as (H, W, C) float32: cv2
    drops a single channel's axis (sh_bands 1) and mistakes more than 128 channels for a
    2-D image (sh_bands 12), so those go in chunks; C <= 128 is one call, as before."""
    c = image.shape[2]
    chunks = []
    for start in range(0, c, REMAP_MAX_CHANNELS):
        part = np.ascontiguousarray(image[..., start : start + REMAP_MAX_CHANNELS])
        out = cv2.remap(part, map_x, map_y, cv2.INTER_LINEAR)
        chunks.append(out.reshape(*map_x.shape, part.shape[2]))
    return chunks[0] if len(chunks) == 1 else np.concatenate(chunks, axis=2)


def upsample_transfer(result: TransferResult, valid_full: np.ndarray) -> TransferResult:
    """Sub-sampled transfer -> every pixel of the image ("OursFast": up-sampling in image
    space), by normalised bilinear interpolation between the valid grid points.

    valid_full: (H, W) bool, pixels with geometry (depth and normal). A pixel is kept when
    all grid points around it are valid, so no transfer is borrowed across a hole or a
    depth edge the grid saw. Identity when the grid is already full resolution.
    """
    h, w = valid_full.shape
    hs, ws = result.valid.shape
    if hs == h and ws == w:
        return result
    # fractional grid index of every pixel (exact also for the clamped last row/column)
    map_u = np.interp(np.arange(w), result.pixel_u, np.arange(ws)).astype(np.float32)
    map_v = np.interp(np.arange(h), result.pixel_v, np.arange(hs)).astype(np.float32)
    map_x = np.ascontiguousarray(np.broadcast_to(map_u[None, :], (h, w)))
    map_y = np.ascontiguousarray(np.broadcast_to(map_v[:, None], (h, w)))
    weight = result.valid.astype(np.float32)
    transfer = _remap_channels(
        np.asarray(result.transfer * weight[..., None], np.float32), map_x, map_y
    )
    den = cv2.remap(weight, map_x, map_y, cv2.INTER_LINEAR)
    keep = valid_full & (den > 0.999)
    # normalised, and zero where not kept, in place (float32 throughout)
    inv = np.where(keep, 1.0 / np.maximum(den, 1e-6), 0.0).astype(np.float32)
    transfer *= inv[..., None]
    bounce = None
    if result.bounce is not None:
        bounce = cv2.remap(
            np.asarray(result.bounce * weight, np.float32), map_x, map_y, cv2.INTER_LINEAR
        )
        bounce *= inv
    return TransferResult(transfer, keep, np.arange(w), np.arange(h), bounce)


@dataclass
class TransferSamples:
    """The transfer at a list of pixels: pixel_v, pixel_u (K,) int64 full-resolution
    coordinates; transfer (K, C) float32; bounce (K,) float32 or None."""

    pixel_v: np.ndarray
    pixel_u: np.ndarray
    transfer: np.ndarray
    bounce: np.ndarray | None


QUADRATURE_TABLE_SIZE = 128  # texels per side of the octahedral table of the correction


def _octahedral_uv(n: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel coordinates (float32) of unit vectors (K, 3) in a size x size octahedral map
    of -n (so normals facing a camera, z < 0, fill the map's centre, away from its seams)."""
    m = -np.asarray(n, np.float64)
    m = m / np.maximum(np.abs(m).sum(axis=1, keepdims=True), 1e-12)
    x, y = m[:, 0], m[:, 1]
    lower = m[:, 2] < 0.0
    fx = np.where(lower, (1.0 - np.abs(y)) * np.where(x >= 0, 1.0, -1.0), x)
    fy = np.where(lower, (1.0 - np.abs(x)) * np.where(y >= 0, 1.0, -1.0), y)
    return (
        ((fx + 1.0) * 0.5 * size - 0.5).astype(np.float32),
        ((fy + 1.0) * 0.5 * size - 0.5).astype(np.float32),
    )


def _octahedral_directions(size: int) -> np.ndarray:
    """(size, size, 3) unit vectors n at the texel centres of `_octahedral_uv`'s map."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    fx, fy = np.meshgrid(c, c)
    fz = 1.0 - np.abs(fx) - np.abs(fy)
    lower = fz < 0.0
    x = np.where(lower, (1.0 - np.abs(fy)) * np.where(fx >= 0, 1.0, -1.0), fx)
    y = np.where(lower, (1.0 - np.abs(fx)) * np.where(fy >= 0, 1.0, -1.0), fy)
    m = np.stack([x, y, fz], axis=-1)
    return -m / np.linalg.norm(m, axis=-1, keepdims=True)


def quadrature_error_table(
    pattern: SamplingPattern, bands: int, size: int = QUADRATURE_TABLE_SIZE
) -> np.ndarray:
    """(size, size, C) float32: `unoccluded_quadrature_error` of the pattern's directions
    (camera frame) at the texel centres of an octahedral map of normals (camera frame).
    Made once per session: the pattern is fixed in the camera frame."""
    normals = _octahedral_directions(size).reshape(-1, 3)
    table = unoccluded_quadrature_error(normals, pattern.directions, bands)
    return table.reshape(size, size, -1).astype(np.float32)


def with_exact_unoccluded(
    samples: TransferSamples,
    normals_cam: np.ndarray,
    world_from_cam: np.ndarray,
    table: np.ndarray,
) -> TransferSamples:
    """The samples' transfer plus `unoccluded_quadrature_error` of their own normals (the
    control variate, TransferParams.rt_exact_unoccluded): the unoccluded part of each
    vector becomes the exact clamped-cosine transfer; blocked directions keep their SSDO
    estimate. normals_cam: (H, W, 3) camera frame (the samples' pixels index it); table:
    `quadrature_error_table` of the session's pattern, looked up bilinearly at each normal
    (camera frame) and rotated into the world frame of the transfer."""
    if not len(samples.pixel_v):
        return samples
    n = np.asarray(normals_cam[samples.pixel_v, samples.pixel_u], np.float64)
    ok = np.linalg.norm(n, axis=1) > 1e-6
    size = table.shape[0]
    map_x, map_y = _octahedral_uv(n[ok], size)
    # edge texels held (not blended with zero), and the lookups laid out as rows of 256
    # (cv2.remap takes maps shorter than 32767 on each side)
    k = len(map_x)
    rows = -(-k // 256)
    maps = [
        np.pad(np.clip(m, 0.0, size - 1.0), (0, rows * 256 - k)).reshape(rows, 256)
        for m in (map_x, map_y)
    ]
    correction_cam = _remap_channels(table, *maps).reshape(rows * 256, -1)[:k]
    rotation = sh.rotation_matrix(
        np.asarray(world_from_cam, np.float64)[:3, :3], sh.bands_of(table.shape[2])
    ).astype(np.float32)
    transfer = np.array(samples.transfer, copy=True)
    transfer[ok] += correction_cam @ rotation.T
    return dataclasses.replace(samples, transfer=transfer)


def random_pixels(mask: np.ndarray, max_pixels: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) int64 of the True pixels of `mask`, row-major; above `max_pixels` a
    seeded uniform random subset of that many (still row-major)."""
    flat = np.flatnonzero(mask)
    if len(flat) > max_pixels:
        flat = np.sort(np.random.default_rng(seed).choice(flat, max_pixels, replace=False))
    rows, cols = np.divmod(flat, mask.shape[1])
    return rows.astype(np.int64), cols.astype(np.int64)


def transfer_samples(
    result: TransferResult, valid_full: np.ndarray | None, max_pixels: int, seed: int
) -> TransferSamples:
    """`interpolated_samples` without edge refinement: the samples only."""
    return interpolated_samples(result, valid_full, max_pixels, seed)[0]


def interpolated_samples(
    result: TransferResult,
    valid_full: np.ndarray | None,
    max_pixels: int,
    seed: int,
    edge_spread: float = 0.0,
) -> tuple[TransferSamples, tuple[np.ndarray, np.ndarray]]:
    """The pixels the light estimate may use, at most `max_pixels` of them (a seeded random
    subset above that; neighbouring pixels repeat each other), with their transfer.

    valid_full: (H, W) bool pixels with geometry, for a sub-sampled grid to be interpolated
    at every such pixel ("OursFast"): the same normalised bilinear interpolation as
    `upsample_transfer`, evaluated at the chosen pixels only (a pixel is kept when every
    grid point around it is valid). None: the grid points themselves.

    edge_spread > 0 (TransferParams.rt_refine_spread): the chosen pixels whose grid points'
    transfers differ by more than edge_spread (the largest distance of a corner's vector
    from their mean, relative to the mean's length: a shadow or crease edge) are returned
    apart, as (rows, cols), for their own transfer. (Pixels beside an invalid grid point
    stay dropped: giving them their own transfer, on dev_d, raised the error by a degree;
    they lie on depth edges, where depth and normals are least reliable.) 0: none.
    """
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    hs, ws = result.valid.shape
    interpolate = valid_full is not None and (hs, ws) != valid_full.shape
    rows, cols = random_pixels(valid_full if interpolate else result.valid, max_pixels, seed)
    bounce = result.bounce
    if not interpolate:
        pv = np.asarray(result.pixel_v)[rows]
        pu = np.asarray(result.pixel_u)[cols]
        return TransferSamples(
            pv.astype(np.int64),
            pu.astype(np.int64),
            result.transfer[rows, cols],
            None if bounce is None else bounce[rows, cols],
        ), none
    gu = np.interp(cols, result.pixel_u, np.arange(ws))  # fractional grid coordinates
    gv = np.interp(rows, result.pixel_v, np.arange(hs))
    u0 = np.minimum(np.floor(gu).astype(np.int64), ws - 1)
    v0 = np.minimum(np.floor(gv).astype(np.int64), hs - 1)
    u1, v1 = np.minimum(u0 + 1, ws - 1), np.minimum(v0 + 1, hs - 1)
    fu, fv = (gu - u0).astype(np.float32), (gv - v0).astype(np.float32)
    corners = [
        (v0, u0, (1 - fv) * (1 - fu)),
        (v0, u1, (1 - fv) * fu),
        (v1, u0, fv * (1 - fu)),
        (v1, u1, fv * fu),
    ]
    den = np.zeros(len(rows), np.float32)
    num = np.zeros((len(rows), result.transfer.shape[-1]), np.float32)
    num_b = None if bounce is None else np.zeros(len(rows), np.float32)
    flat_t = result.transfer.reshape(hs * ws, -1)
    flat_valid = result.valid.reshape(-1)
    flat_b = None if bounce is None else bounce.reshape(-1)
    for v, u, wgt in corners:
        at = v * ws + u  # np.take on the flattened grid: cheaper than 2-D fancy indexing
        wv = wgt * np.take(flat_valid, at)
        den += wv
        num += wv[:, None] * np.take(flat_t, at, axis=0)
        if num_b is not None:
            num_b += wv * np.take(flat_b, at)
    keep = den > 0.999
    edges = none
    if edge_spread > 0.0:
        mean = num / np.maximum(den, 1e-6)[:, None]
        spread = np.zeros(len(rows), np.float32)
        for v, u, wgt in corners:  # the corners the pixel's interpolation reads
            at = v * ws + u
            gap = np.linalg.norm(np.take(flat_t, at, axis=0) - mean, axis=1)
            spread = np.maximum(spread, np.where(np.take(flat_valid, at) & (wgt > 0), gap, 0.0))
        sharp = keep & (spread > edge_spread * np.linalg.norm(mean, axis=1))
        edges = (rows[sharp].astype(np.int64), cols[sharp].astype(np.int64))
        keep &= ~sharp
    inv = 1.0 / den[keep]
    return TransferSamples(
        rows[keep].astype(np.int64),
        cols[keep].astype(np.int64),
        num[keep] * inv[:, None],
        None if num_b is None else num_b[keep] * inv,
    ), edges


def _occlusion_reference(x: np.ndarray, s: np.ndarray, w: np.ndarray, chi: float) -> float:
    """K of eq. 7-8 (NumPy): occluding surface point s (3,) seen from x (3,) towards w (3,)."""
    t = s - x
    norm = float(np.linalg.norm(t))
    if norm < 1e-9:
        return 1.0
    return min(chi, 1.0 - float(t @ w) / norm) / chi


def _visibility_reference(
    x: np.ndarray,
    w: np.ndarray,
    radius: float,
    depth: np.ndarray,
    camera: PinholeCamera,
    aux: AuxBufferArrays,
    chi: float,
    thickness: float,
) -> float:
    """K in [0, 1] of one sample y = x + radius * w against the main and auxiliary buffers."""
    y = x + radius * w
    k = 1.0
    h, width = depth.shape
    if y[2] > 1e-6:
        u = int(round(camera.fx * y[0] / y[2] + camera.cx))
        v = int(round(camera.fy * y[1] / y[2] + camera.cy))
        if 0 <= u < width and 0 <= v < h:
            sz = float(depth[v, u])
            if 0.0 < sz < y[2] - (BIAS_ABS_M + BIAS_REL * y[2]) and sz > y[2] - thickness:
                s = np.array(
                    [(u - camera.cx) / camera.fx * sz, (v - camera.cy) / camera.fy * sz, sz]
                )
                k = min(k, _occlusion_reference(x, s, w, chi))
    for b in range(aux.depth.shape[0]):
        rot, trans = aux.buffer_from_cam[b, :, :3], aux.buffer_from_cam[b, :, 3]
        q = rot @ y + trans  # sample in the buffer frame
        r = aux.depth.shape[1]
        half = 0.5 * (r - 1)
        pix = float(aux.pixel_size[b])
        ub, vb = int(round(q[0] / pix + half)), int(round(q[1] / pix + half))
        if 0 <= ub < r and 0 <= vb < r:
            sd = float(aux.depth[b, vb, ub])
            if 0.0 < sd < q[2] - (BIAS_ABS_M + BIAS_REL * 0.5 * sd) and sd > q[2] - thickness:
                s_buffer = np.array([(ub - half) * pix, (vb - half) * pix, sd])
                s = rot.T @ (s_buffer - trans)  # back into the camera frame
                k = min(k, _occlusion_reference(x, s, w, chi))
    return k


def transfer_reference(
    points_cam: np.ndarray,
    normals_cam: np.ndarray,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    pattern: SamplingPattern,
    aux: AuxBufferArrays | None,
    params: TransferParams,
    plane: SupportPlane | None = None,
) -> TransferResult:
    """Plain NumPy/Python oracle of :func:`compute_transfer`: same inputs, same definition
    (the transfer only, not the bounce).

    A straightforward loop over grid pixels, directions and steps; very slow, for tests on
    tiny images only.
    """
    points = np.asarray(points_cam, dtype=np.float32).astype(np.float64)
    normals = np.asarray(normals_cam, dtype=np.float32).astype(np.float64)
    depth = points[..., 2]
    h, w = depth.shape
    step = params.rt_subsample
    hs, ws = (h + step - 1) // step, (w + step - 1) // step
    u_grid = np.array([min(j * step + step // 2, w - 1) for j in range(ws)])
    v_grid = np.array([min(i * step + step // 2, h - 1) for i in range(hs)])
    dirs = np.asarray(pattern.directions, dtype=np.float64)
    rot_world_cam = np.asarray(world_from_cam, dtype=np.float64)[:3, :3]
    ysh = sh.sh_basis(dirs @ rot_world_cam.T, params.sh_bands)  # basis in the WORLD frame
    aux = aux if aux is not None else AuxBufferArrays.empty()
    weight = 4.0 * math.pi / len(dirs)
    transfer = np.zeros((hs, ws, ysh.shape[1]))
    valid = np.zeros((hs, ws), dtype=bool)
    for i, vi in enumerate(v_grid):
        for jj, ui in enumerate(u_grid):
            x, n = points[vi, ui], normals[vi, ui]
            if not x[2] > 0.0 or not np.any(n != 0.0):
                continue
            valid[i, jj] = True
            above_plane = plane is not None and plane.height(x) > -HORIZON_BELOW_M
            for j, wdir in enumerate(dirs):
                cos_n = float(wdir @ n)
                if not cos_n > 0.0 or (above_plane and float(wdir @ plane.up) < 0.0):
                    continue
                k = 1.0
                if params.visibility:
                    for s in range(pattern.radii.shape[3]):
                        radius = float(pattern.radii[vi % 2, ui % 2, j, s])
                        k = min(
                            k,
                            _visibility_reference(
                                x,
                                wdir,
                                radius,
                                depth,
                                camera,
                                aux,
                                visibility_ramp(pattern, params),
                                params.rt_thickness_m,
                            ),
                        )
                transfer[i, jj] += k * cos_n * weight * ysh[j]
    return TransferResult(transfer.astype(np.float32), valid, u_grid, v_grid)
