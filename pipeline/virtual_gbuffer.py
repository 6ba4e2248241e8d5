"""Geometry buffers of the virtual objects, by ray casting their meshes (Open3D).

The renderer needs, per camera pixel, the depth, normal and albedo of the nearest virtual
surface (to depth-test it against the filtered real depth G_r), and for each auxiliary
orthographic buffer the depth of the virtual surfaces seen from it (so that virtual objects
also shadow where the camera does not see them). Both come from one Open3D
`RaycastingScene` of the scene's meshes in the world frame, built once per scene.

Ray casting rather than rasterising: it is already a dependency, needs no GPU or GL context,
gives exact per-pixel hits, and costs only the rays of the pixels that the objects' bounding
spheres cover (measured in `arlight bench`, Rendering stage).

Frames: camera buffers are in the OpenCV camera frame of the frame being rendered; depth is
along the optical axis (metres, 0 = no virtual surface).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from arlight.core.camera import PinholeCamera
from arlight.pipeline.virtual_scene import VirtualScene

NEAR_M = 0.01  # virtual surfaces closer to the camera than this are clipped


@dataclass
class VirtualGBuffer:
    """The nearest virtual surface per pixel of the camera image.

    depth_m: (H, W) float32 along the optical axis, 0 where no object is hit;
    normals_cam: (H, W, 3) float32 unit normals facing the camera (two-sided), camera frame;
    albedo: (H, W, 3) float32 linear RGB; object_index: (H, W) int32, -1 where none.
    """

    depth_m: np.ndarray
    normals_cam: np.ndarray
    albedo: np.ndarray
    object_index: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.object_index >= 0


def texel_origins(
    world_from_buffer: np.ndarray,
    resolution: int,
    pixel_size_m: float,
    rows: slice = slice(None),
    cols: slice = slice(None),
) -> np.ndarray:
    """(K, 3) world points of an orthographic buffer's texel centres on its image plane,
    row-major (the layout of `aux_buffers.OrthoBuffer`), of the texels in rows x cols (all
    R * R by default); their rays run along its +z."""
    half = (resolution - 1) / 2.0
    coords = (np.arange(resolution) - half) * pixel_size_m
    xx, yy = np.meshgrid(coords[cols], coords[rows])
    local = np.stack([xx, yy, np.zeros_like(xx)], axis=-1).reshape(-1, 3)
    return local @ world_from_buffer[:3, :3].T + world_from_buffer[:3, 3]


class VirtualRaycaster:
    """Ray casting of one virtual scene (world frame), reused for every frame."""

    def __init__(self, scene: VirtualScene):
        self.scene = scene
        self._rays = o3d.t.geometry.RaycastingScene()
        self._normals: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._geometry_object: dict[int, int] = {}
        for index, obj in enumerate(scene.objects):
            vertices = o3c.Tensor(obj.world_vertices().astype(np.float32))
            triangles = o3c.Tensor(obj.triangles.astype(np.uint32))
            gid = self._rays.add_triangles(vertices, triangles)
            self._geometry_object[int(gid)] = index
            self._normals.append(obj.world_normals())
            self._triangles.append(obj.triangles)
        self._albedo = np.array(
            [o.material.albedo for o in scene.objects] or [(0.0, 0.0, 0.0)], np.float32
        )
        self._spheres = [o.bounding_sphere() for o in scene.objects]

    def _cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        return self._rays.cast_rays(o3c.Tensor(rays))

    def _hit_normals(self, hits: dict, n_rays: int) -> tuple[np.ndarray, np.ndarray]:
        """(object index (K,), world normals (K, 3)) from interpolated vertex normals."""
        gid = hits["geometry_ids"].numpy().astype(np.int64)
        prim = hits["primitive_ids"].numpy().astype(np.int64)
        uv = hits["primitive_uvs"].numpy().astype(np.float64)
        found = gid != o3d.t.geometry.RaycastingScene.INVALID_ID
        index = np.full(n_rays, -1, np.int32)
        normals = np.zeros((n_rays, 3))
        for geometry, obj in self._geometry_object.items():
            sel = np.flatnonzero(found & (gid == geometry))
            if not len(sel):
                continue
            index[sel] = obj
            tri = self._triangles[obj][prim[sel]]
            vn = self._normals[obj]
            u, v = uv[sel, 0:1], uv[sel, 1:2]
            n = (1.0 - u - v) * vn[tri[:, 0]] + u * vn[tri[:, 1]] + v * vn[tri[:, 2]]
            normals[sel] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return index, normals

    def screen_rect(
        self, camera: PinholeCamera, world_from_cam: np.ndarray, margin_m: float = 0.0
    ) -> tuple[int, int, int, int] | None:
        """(u0, v0, u1, v1), end exclusive, covering every object's bounding sphere grown by
        margin_m, clipped to the image; None when no object can be in view."""
        cam_from_world = np.linalg.inv(world_from_cam)
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        rects = []
        for centre, radius in self._spheres:
            # the cube around the sphere: where all its corners are in front of the camera,
            # the hull of their projections bounds the sphere's silhouette
            c = cam_from_world[:3, :3] @ centre + cam_from_world[:3, 3]
            box = c + (radius + margin_m) * corners
            if np.all(box[:, 2] <= NEAR_M):
                continue  # wholly behind the camera
            if np.any(box[:, 2] <= NEAR_M):
                return 0, 0, camera.width, camera.height  # around the camera: all of it
            u = camera.fx * box[:, 0] / box[:, 2] + camera.cx
            v = camera.fy * box[:, 1] / box[:, 2] + camera.cy
            rects.append((u.min(), v.min(), u.max(), v.max()))
        if not rects:
            return None
        u0 = max(0, int(np.floor(min(r[0] for r in rects))) - 1)
        v0 = max(0, int(np.floor(min(r[1] for r in rects))) - 1)
        u1 = min(camera.width, int(np.ceil(max(r[2] for r in rects))) + 2)
        v1 = min(camera.height, int(np.ceil(max(r[3] for r in rects))) + 2)
        if u0 >= u1 or v0 >= v1:
            return None
        return u0, v0, u1, v1

    def camera_gbuffer(self, camera: PinholeCamera, world_from_cam: np.ndarray) -> VirtualGBuffer:
        """The virtual surfaces seen by the camera (rays only inside `screen_rect`)."""
        h, w = camera.height, camera.width
        out = VirtualGBuffer(
            np.zeros((h, w), np.float32),
            np.zeros((h, w, 3), np.float32),
            np.zeros((h, w, 3), np.float32),
            np.full((h, w), -1, np.int32),
        )
        rect = self.screen_rect(camera, world_from_cam)
        if rect is None:
            return out
        u0, v0, u1, v1 = rect
        uu, vv = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
        rays_cam = np.stack(
            [
                (uu - camera.cx) / camera.fx,
                (vv - camera.cy) / camera.fy,
                np.ones_like(uu, dtype=np.float64),
            ],
            axis=-1,
        ).reshape(-1, 3)
        rot, origin = world_from_cam[:3, :3], world_from_cam[:3, 3]
        # rays of unit z in the camera frame: t_hit is then the depth along the optical axis;
        # starting at NEAR_M clips what is closer
        starts = origin + NEAR_M * rays_cam @ rot.T
        hits = self._cast(starts, rays_cam @ rot.T)
        t = hits["t_hit"].numpy().astype(np.float64) + NEAR_M
        index, normals = self._hit_normals(hits, len(rays_cam))
        ok = (index >= 0) & np.isfinite(t)
        normals_cam = normals @ rot  # world -> camera: R^T n, row-wise
        facing = np.einsum("ij,ij->i", normals_cam, rays_cam) > 0.0
        normals_cam[facing] *= -1.0  # two-sided: the side the camera sees
        shape = (v1 - v0, u1 - u0)
        out.depth_m[v0:v1, u0:u1] = np.where(ok, t, 0.0).reshape(shape)
        out.normals_cam[v0:v1, u0:u1] = np.where(ok[:, None], normals_cam, 0.0).reshape(*shape, 3)
        out.object_index[v0:v1, u0:u1] = np.where(ok, index, -1).reshape(shape)
        out.albedo[v0:v1, u0:u1] = np.where(
            ok[:, None], self._albedo[np.maximum(index, 0)], 0.0
        ).reshape(*shape, 3)
        return out

    def orthographic_depth(
        self, world_from_buffer: np.ndarray, resolution: int, pixel_size_m: float
    ) -> np.ndarray:
        """(R, R) float32 depth along the buffer's +z from its image plane to the first
        virtual surface (0 = none), in the layout of `aux_buffers.OrthoBuffer`."""
        rot, trans = world_from_buffer[:3, :3], world_from_buffer[:3, 3]
        out = np.zeros((resolution, resolution), np.float32)
        # only the texels whose ray can meet an object's bounding sphere are cast (a few of
        # the buffer's 4 m: 6 -> 1 ms a frame for 4 buffers); the rest see nothing
        rows, cols = self._texels_near_objects(rot, trans, resolution, pixel_size_m)
        if rows.stop > rows.start and cols.stop > cols.start:
            origins = texel_origins(world_from_buffer, resolution, pixel_size_m, rows, cols)
            directions = np.broadcast_to(rot[:, 2], origins.shape)
            t = self._cast(origins, directions)["t_hit"].numpy()
            out[rows, cols] = np.where(np.isfinite(t), t, 0.0).reshape(out[rows, cols].shape)
        return out

    def _texels_near_objects(
        self, rot: np.ndarray, trans: np.ndarray, resolution: int, pixel_size_m: float
    ) -> tuple[slice, slice]:
        """(rows, cols) of an orthographic buffer (its axes `rot`, image plane through
        `trans`) holding every texel whose ray (+z from the plane) can meet an object's
        bounding sphere; empty slices when none can."""
        half = (resolution - 1) / 2.0
        lo = np.full(2, np.inf)
        hi = np.full(2, -np.inf)
        for centre, radius in self._spheres:
            local = rot.T @ (np.asarray(centre, np.float64) - trans)  # buffer frame
            if local[2] + radius < 0.0:
                continue  # wholly behind the image plane: no ray starts before it
            lo = np.minimum(lo, (local[:2] - radius) / pixel_size_m + half)
            hi = np.maximum(hi, (local[:2] + radius) / pixel_size_m + half)
        if not np.all(np.isfinite(lo)):
            return slice(0, 0), slice(0, 0)
        first = np.clip(np.floor(lo).astype(int) - 1, 0, resolution)
        last = np.clip(np.ceil(hi).astype(int) + 2, 0, resolution)
        return slice(first[1], last[1]), slice(first[0], last[0])

    def first_hits(
        self, origins_world: np.ndarray, directions_world: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The first virtual surface along each ray (world frame): (distance (K,) metres, inf
        = none; object index (K,) int32, -1 = none; unit world normals (K, 3), interpolated,
        as stored: not turned towards the ray)."""
        n = len(directions_world)
        if n == 0:
            return np.zeros(0), np.zeros(0, np.int32), np.zeros((0, 3))
        d = np.asarray(directions_world, np.float64)
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        hits = self._cast(np.asarray(origins_world, np.float64), d)
        t = hits["t_hit"].numpy().astype(np.float64)
        index, normals = self._hit_normals(hits, n)
        return np.where(index >= 0, t, np.inf), index, normals

    def bounding_spheres(self) -> list[tuple[np.ndarray, float]]:
        """Per object: (centre (3,) world, radius) metres of its bounding sphere."""
        return list(self._spheres)

    def distance_to_spheres(self, points_world: np.ndarray) -> np.ndarray:
        """(K,) distance (metres) from each world point to the nearest object's bounding
        sphere (negative inside): a cheap lower bound of `distance_to_objects`."""
        best = np.full(len(points_world), np.inf)
        for centre, radius in self._spheres:
            best = np.minimum(best, np.linalg.norm(points_world - centre, axis=1) - radius)
        return best

    def distance_to_objects(self, points_world: np.ndarray) -> np.ndarray:
        """(K,) distance (metres) from each world point to the nearest virtual surface."""
        if not len(points_world):
            return np.zeros(0)
        query = o3c.Tensor(np.ascontiguousarray(points_world, dtype=np.float32))
        return self._rays.compute_distance(query).numpy().astype(np.float64)
