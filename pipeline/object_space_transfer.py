"""Object-space radiance transfer: visibility by rays against the reconstructed surface.

A comparator for the image-space SSDO transfer (radiance_transfer.py), in the spirit of the
object-space methods the paper measures itself against (GR12/GR14 in seeds/000, table 1):
for a visible surface point x with normal n (a pixel of the filtered depth G_r, on the
same sub-sampled grid as SSDO) and the SAME N directions w_j (the session's
SamplingPattern),

    T_z(x) = sum_j V(x, w_j) max(0, n . w_j) Y_z(w_j) 4 pi / N

with a binary visibility V: 0 when the ray from x + b n (b = the SSDO depth-test bias,
BIAS_ABS_M + BIAS_REL * depth) meets the surface at a distance in [BIAS_ABS_M,
rt_radius_m] (rays of limited length, as GR12/GR14: distant geometry does not shadow),
else 1. The SH basis is evaluated on the directions rotated into the WORLD frame, as in
SSDO, so the result (`TransferResult`) goes to LightEst and up-sampling unchanged. SSDO's
sample radii, steps, thickness and continuous K (eq. 7-9) play no part here.

The surface: the TSDF volume's marching-cubes mesh (world frame,
`VolumeReconstruction.triangle_mesh`) when the volume is on, else a mesh of the current
filtered depth (camera frame, `depth_mesh`: the pixel grid triangulated, triangles across
depth edges dropped), in an Open3D `RaycastingScene` (Embree, CPU). Rays are cast in
batches: `test_occlusions` (any hit within the ray's length) for V, then `cast_rays` only
on the blocked rays for the hit points of the one-bounce light: for a blocked direction the
occluder brings max(0, n . w) I(s) 4 pi / N, with I(s) the image luminance where the hit
point s projects (as SSDO, whatever surface is seen at that pixel; nothing when it falls
outside the image). With a support plane (rt_horizon), an unblocked direction below its
horizon adds the ground's median luminance to the bounce and nothing to the transfer.

Cost, measured on 2 cores at 640x480 with 64 directions at every pixel (`full`; dev_a of
the shared set): about 7 million rays a frame (4.5 % of them blocked); Embree's occlusion
test of them takes about 0.23 s (some 30 million rays a second), the hit points of the
blocked ones 0.04 s, building the rays and summing the transfer (Numba) about 0.1 s:
RadTransfer about 0.4 s against SSDO's 0.3. The scene costs on top: the volume's mesh
(about 0.15 s at 256^3, 200k triangles) and its BVH (about 0.1 s) are rebuilt only once the
volume has fused `aux_update_interval` more frames since the last build (or was reset),
and cost nothing in between; the depth mesh (up to 600k triangles at 640x480, about 0.2 s
with its BVH) is the current frame's, so it is rebuilt every frame.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
import open3d as o3d
import open3d.core as o3c

from arlight.core.camera import PinholeCamera
from arlight.pipeline import sh
from arlight.pipeline.channels import any_nonzero
from arlight.pipeline.config import TransferParams
from arlight.pipeline.horizon import SupportPlane
from arlight.pipeline.radiance_transfer import (
    BIAS_ABS_M,
    BIAS_REL,
    HORIZON_BELOW_M,
    SamplingPattern,
    TransferResult,
    plane_arrays,
)

if TYPE_CHECKING:
    from arlight.pipeline.reconstruction import VolumeReconstruction

log = logging.getLogger(__name__)

# depth_mesh: a triangle whose vertex depths differ by more than this fraction of the
# nearest one spans a depth edge (a surface at 2 m seen at 85 degrees changes by ~2 % a pixel)
DEPTH_EDGE_REL = 0.05
# rays per test_occlusions call: bounds a batch's memory (about 40 bytes a ray: the ray,
# its result and luminance) without a measurable cost per call
RAY_BATCH = 1 << 20


@dataclass(frozen=True)
class SurfaceMesh:
    """vertices (M, 3) float32 metres; triangles (K, 3) int32 indices into vertices;
    in_world: vertices in the world frame (the volume's mesh) or the camera frame (a depth
    image's mesh)."""

    vertices: np.ndarray
    triangles: np.ndarray
    in_world: bool

    @property
    def empty(self) -> bool:
        return len(self.triangles) == 0


class OcclusionScene:
    """A SurfaceMesh in an Open3D RaycastingScene (its BVH is built here, once)."""

    def __init__(self, mesh: SurfaceMesh):
        self.mesh = mesh
        self.in_world = mesh.in_world
        self._scene = None
        if not mesh.empty:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(
                o3c.Tensor(np.ascontiguousarray(mesh.vertices, np.float32)),
                o3c.Tensor(np.ascontiguousarray(mesh.triangles).astype(np.uint32)),
            )
            # Embree builds the BVH on the first query: make that part of the build's cost
            self._scene.test_occlusions(o3c.Tensor(np.zeros((1, 6), np.float32)))

    def blocked(self, rays: np.ndarray, tnear: float, tfar: float) -> np.ndarray:
        """(R,) bool: a hit at a distance in [tnear, tfar] along rays (R, 6) float32
        (origin, unit direction, the mesh's frame). All False for an empty mesh."""
        if self._scene is None or len(rays) == 0:
            return np.zeros(len(rays), bool)
        return self._scene.test_occlusions(o3c.Tensor.from_numpy(rays), tnear, tfar).numpy()

    def first_hit(self, rays: np.ndarray) -> np.ndarray:
        """(R,) float32 distance to the first hit along rays (R, 6) (inf: none)."""
        if self._scene is None or len(rays) == 0:
            return np.full(len(rays), np.inf, np.float32)
        return self._scene.cast_rays(o3c.Tensor.from_numpy(rays))["t_hit"].numpy()


def depth_mesh(points_cam: np.ndarray) -> SurfaceMesh:
    """The pixel grid of a depth image's points triangulated (two triangles per 2x2 block
    of valid pixels), camera frame; triangles across depth edges (DEPTH_EDGE_REL) dropped.

    points_cam: (H, W, 3) float32 camera-frame points, z = 0 where depth is missing.
    """
    h, w = points_cam.shape[:2]
    z = points_cam[..., 2]
    index = np.arange(h * w, dtype=np.int32).reshape(h, w)
    corners = [
        (slice(0, -1), slice(0, -1)),
        (slice(1, None), slice(0, -1)),
        (slice(0, -1), slice(1, None)),
        (slice(1, None), slice(1, None)),
    ]
    ids = [index[c].ravel() for c in corners]  # a = (r, c), b = (r+1, c), c' = (r, c+1), d
    zs = [z[c].ravel() for c in corners]
    triangles = []
    for i, j, k in ((0, 1, 2), (2, 1, 3)):  # (a, b, c') and (c', b, d)
        lo = np.minimum(np.minimum(zs[i], zs[j]), zs[k])
        hi = np.maximum(np.maximum(zs[i], zs[j]), zs[k])
        keep = (lo > 0) & (hi - lo <= DEPTH_EDGE_REL * lo)
        triangles.append(np.stack([ids[i][keep], ids[j][keep], ids[k][keep]], axis=1))
    return SurfaceMesh(
        np.ascontiguousarray(points_cam.reshape(-1, 3), np.float32),
        np.concatenate(triangles),
        in_world=False,
    )


def object_space_transfer(
    points_cam: np.ndarray,
    normals_cam: np.ndarray,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    pattern: SamplingPattern,
    scene: OcclusionScene | None,
    params: TransferParams,
    luminance: np.ndarray | None = None,
    plane: SupportPlane | None = None,
) -> TransferResult:
    """SH transfer with ray-cast visibility for every `params.rt_subsample`-th pixel.

    points_cam: (H, W, 3) float32 camera-frame points (z = 0 missing); normals_cam: (H, W, 3)
    unit normals, camera frame, zeros where unknown; world_from_cam (4, 4); pattern: the
    directions (camera frame) as SSDO uses them; scene: the surface to cast against (None,
    or params.visibility False: V = 1); luminance: optional (H, W) linear luminance, for the
    one-bounce light (TransferResult.bounce); plane: optional support plane (camera frame).
    Same grid and output as `radiance_transfer.compute_transfer`.
    """
    h, w = points_cam.shape[:2]
    step = params.rt_subsample
    hs, ws = (h + step - 1) // step, (w + step - 1) // step
    u = np.minimum(np.arange(ws) * step + step // 2, w - 1)
    v = np.minimum(np.arange(hs) * step + step // 2, h - 1)
    pts = np.asarray(points_cam, np.float32)[np.ix_(v, u)].reshape(-1, 3).astype(np.float64)
    nrm = np.asarray(normals_cam, np.float32)[np.ix_(v, u)].reshape(-1, 3).astype(np.float64)
    valid = (pts[:, 2] > 0.0) & any_nonzero(nrm)
    world_from_cam = np.asarray(world_from_cam, np.float64)
    dirs = np.ascontiguousarray(pattern.directions, np.float64)  # (N, 3), camera frame
    ysh = sh.sh_basis(dirs @ world_from_cam[:3, :3].T, params.sh_bands)  # world-frame basis
    transfer = np.zeros((hs * ws, ysh.shape[1]))
    bounce = np.zeros(hs * ws)
    plane_arr, ground_lum = plane_arrays(plane, luminance)
    up = plane_arr[:3]
    above = np.zeros(hs * ws, bool)
    if plane is not None:  # points on or above the plane: its horizon hides the light
        above = pts @ up + plane_arr[3] > -HORIZON_BELOW_M
    cast = scene if params.visibility else None
    mesh_from_cam = world_from_cam if cast is not None and cast.in_world else np.eye(4)
    rows = np.flatnonzero(valid)
    per_batch = max(1, RAY_BATCH // len(dirs))
    for start in range(0, len(rows), per_batch):
        batch = rows[start : start + per_batch]
        x, n = pts[batch], np.ascontiguousarray(nrm[batch])
        counts = np.zeros(len(batch), np.int64)
        _count_lit(n, dirs, counts)  # directions with n . w > 0, per pixel
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        blocked = np.zeros(int(counts.sum()), bool)
        ray_lum = np.zeros(len(blocked))
        if cast is not None:
            origins = x + (BIAS_ABS_M + BIAS_REL * x[:, 2:3]) * n  # off the surface, along n
            blocked, ray_lum = _cast(
                cast,
                origins,
                n,
                dirs,
                offsets,
                len(blocked),
                mesh_from_cam,
                camera,
                params.rt_radius_m,
                luminance,
            )
        sub_t, sub_b = transfer[batch], bounce[batch]
        _accumulate(
            n,
            above[batch],
            dirs,
            up,
            ysh,
            4.0 * math.pi / len(dirs),
            offsets,
            blocked,
            ray_lum,
            ground_lum,
            sub_t,
            sub_b,
        )
        transfer[batch], bounce[batch] = sub_t, sub_b
    return TransferResult(
        transfer.reshape(hs, ws, -1).astype(np.float32),
        valid.reshape(hs, ws),
        u,
        v,
        None if luminance is None else bounce.reshape(hs, ws).astype(np.float32),
    )


def _cast(
    scene: OcclusionScene,
    origins_cam: np.ndarray,
    normals_cam: np.ndarray,
    dirs_cam: np.ndarray,
    offsets: np.ndarray,
    count: int,
    mesh_from_cam: np.ndarray,
    camera: PinholeCamera,
    radius_m: float,
    luminance: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The `count` rays from origins_cam[p] (B, 3) towards each dirs_cam[j] (N, 3) with
    normals_cam[p] . w > 0, in that order from offsets[p] on: blocked (R,) bool, and the
    image luminance at the projection of each blocked ray's first hit (R,) (0 elsewhere,
    and everywhere without an image)."""
    rot, trans = mesh_from_cam[:3, :3], mesh_from_cam[:3, 3]
    rays = np.empty((count, 6), np.float32)
    _fill_rays(
        (origins_cam @ rot.T + trans).astype(np.float32),
        normals_cam,
        dirs_cam,
        (dirs_cam @ rot.T).astype(np.float32),
        offsets,
        rays,
    )
    blocked = scene.blocked(rays, BIAS_ABS_M, radius_m)
    lum = np.zeros(count)
    if luminance is None:
        return blocked, lum
    hit_rays = rays[blocked]
    hit_rays[:, :3] += BIAS_ABS_M * hit_rays[:, 3:]  # the first hit beyond tnear
    t = scene.first_hit(hit_rays).astype(np.float64)
    t = np.where(np.isfinite(t), t, radius_m - BIAS_ABS_M)  # (a blocked ray cannot miss)
    hits_m = hit_rays[:, :3].astype(np.float64) + t[:, None] * hit_rays[:, 3:]
    hits_cam = (hits_m - trans) @ rot  # back into the camera frame (rot is a rotation)
    z = hits_cam[:, 2]
    front = z > 1e-6
    col = np.full(len(z), -1, np.int64)
    row = np.full(len(z), -1, np.int64)
    col[front] = np.rint(camera.fx * hits_cam[front, 0] / z[front] + camera.cx)
    row[front] = np.rint(camera.fy * hits_cam[front, 1] / z[front] + camera.cy)
    inside = front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    hit_lum = np.zeros(len(z))
    hit_lum[inside] = luminance[row[inside], col[inside]]
    lum[blocked] = hit_lum
    return blocked, lum


# The per-pixel loops are Numba kernels (no BLAS: its thread pool fights numba's for two
# cores); each visits the directions with n . w > 0 of one pixel in the same order, so the
# k-th ray of pixel p is offsets[p] + k in every array.
@numba.njit(parallel=True, cache=True)
def _count_lit(normals, dirs, counts):
    for p in numba.prange(normals.shape[0]):
        c = 0
        for j in range(dirs.shape[0]):
            if (
                normals[p, 0] * dirs[j, 0] + normals[p, 1] * dirs[j, 1] + normals[p, 2] * dirs[j, 2]
            ) > 0.0:
                c += 1
        counts[p] = c


@numba.njit(parallel=True, cache=True)
def _fill_rays(origins_m, normals, dirs, dirs_m, offsets, rays):
    for p in numba.prange(normals.shape[0]):
        k = offsets[p]
        for j in range(dirs.shape[0]):
            if (
                normals[p, 0] * dirs[j, 0] + normals[p, 1] * dirs[j, 1] + normals[p, 2] * dirs[j, 2]
            ) > 0.0:
                for c in range(3):
                    rays[k, c] = origins_m[p, c]
                    rays[k, 3 + c] = dirs_m[j, c]
                k += 1


@numba.njit(parallel=True, cache=True)
def _accumulate(
    normals, above, dirs, up, ysh, weight, offsets, blocked, ray_lum, ground_lum, transfer, bounce
):
    """transfer[p] += V max(0, n . w) Y(w) weight over the directions (V = not blocked,
    and nothing below the plane's horizon for a point `above` it); bounce[p] += the same
    factor times the hit's luminance (blocked) or ground_lum (below the horizon)."""
    for p in numba.prange(normals.shape[0]):
        k = offsets[p]
        for j in range(dirs.shape[0]):
            cos_n = (
                normals[p, 0] * dirs[j, 0] + normals[p, 1] * dirs[j, 1] + normals[p, 2] * dirs[j, 2]
            )
            if cos_n <= 0.0:
                continue
            f = cos_n * weight
            if blocked[k]:
                bounce[p] += f * ray_lum[k]
            elif above[p] and up[0] * dirs[j, 0] + up[1] * dirs[j, 1] + up[2] * dirs[j, 2] < 0.0:
                bounce[p] += f * ground_lum
            else:
                for c in range(ysh.shape[1]):
                    transfer[p, c] += f * ysh[j, c]
            k += 1


class ObjectSpaceTransfer:
    """One session's ray-cast transfer: the occlusion scene, kept between frames.

    update_interval: the volume's mesh is rebuilt once V has fused this many more frames
    since the last build (the auxiliary buffers' aux_update_interval), or when V was reset;
    without a volume (or while its mesh is empty) the current depth image's mesh is used,
    made every frame. `last_build_ms` and `builds` say what the scene cost.
    """

    def __init__(self, update_interval: int):
        self.update_interval = max(1, int(update_interval))
        self._scene: OcclusionScene | None = None
        self._built_at = -1  # volume.frames_integrated at the last build
        self.builds = 0
        self.last_build_ms = 0.0

    def scene(self, points_cam: np.ndarray, volume: VolumeReconstruction | None) -> OcclusionScene:
        """The surface for this frame (module docstring: when it is rebuilt)."""
        fused = -1 if volume is None else volume.frames_integrated
        if (
            volume is not None
            and self._scene is not None
            and 0 <= self._built_at <= fused
            and fused - self._built_at < self.update_interval
        ):
            return self._scene
        t0 = time.perf_counter()
        mesh = None
        if volume is not None:
            vertices, triangles = volume.triangle_mesh()
            mesh = SurfaceMesh(vertices, triangles, in_world=True)
        cached = mesh is not None and not mesh.empty
        scene = OcclusionScene(mesh if cached else depth_mesh(points_cam))
        self._scene, self._built_at = (scene, fused) if cached else (None, -1)
        self.builds += 1
        self.last_build_ms = (time.perf_counter() - t0) * 1e3
        log.debug(
            "raycast scene: %d triangles (%s) in %.0f ms",
            len(scene.mesh.triangles),
            "volume" if cached else "depth",
            self.last_build_ms,
        )
        return scene

    def compute(
        self,
        points_cam: np.ndarray,
        normals_cam: np.ndarray,
        camera: PinholeCamera,
        world_from_cam: np.ndarray,
        pattern: SamplingPattern,
        params: TransferParams,
        luminance: np.ndarray | None = None,
        plane: SupportPlane | None = None,
        volume: VolumeReconstruction | None = None,
    ) -> TransferResult:
        """`object_space_transfer` against this frame's scene (see `scene`)."""
        scene = self.scene(points_cam, volume) if params.visibility else None
        return object_space_transfer(
            points_cam,
            normals_cam,
            camera,
            world_from_cam,
            pattern,
            scene,
            params,
            luminance,
            plane,
        )
