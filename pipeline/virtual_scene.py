"""Virtual objects to render into the camera image (section 5.4 of seeds/000).

A `VirtualScene` is a tuple of `VirtualObject`s: a triangle mesh in its own object frame
(metres), its pose `world_from_object` (4x4, p_world = M [p_object, 1], may carry a uniform
scale), and a `Material`. An object may instead be *anchored*: placed on the detected
support plane (floor, table) under a pixel of the first frame in which a plane is seen, for
live data whose world frame is the first camera; its pose is resolved then and kept.

Object frame convention (as the shared `ar/` meshes): origin at the centre of the object's
base, +y up; an anchored object stands with its +y along the plane's up direction.

Nothing here reads files (that is `arlight.sources.virtual_scene_file`); the built-in
primitives are made with Open3D.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from arlight.core.checks import CheckError, check_rigid

MAX_TRIANGLES = 2_000_000  # in one scene, all objects together: above it, a clear error
MAX_OBJECTS = 64


class SceneError(CheckError):
    """A virtual scene that cannot be rendered; the message names the object and the cause."""

    def __init__(self, message: str):  # one argument: the message names its own field
        ValueError.__init__(self, message)
        self.field, self.message = "virtual scene", message

    def __reduce__(self):
        return (type(self), (self.message,))


@dataclass(frozen=True)
class Material:
    """Surface of a virtual object. albedo: linear RGB in [0, 1] (Lambertian reflectance).
    roughness / metalness / mirror are carried for image-based lighting; the differential
    renderer shades Lambertian."""

    albedo: tuple[float, float, float] = (0.7, 0.7, 0.7)
    roughness: float = 1.0
    metalness: float = 0.0
    mirror: bool = False


@dataclass(frozen=True)
class Anchor:
    """Place the object on the support plane where the ray through `pixel` (u, v) meets it,
    or at the view's centre when pixel is None, in the first frame that shows a plane.
    yaw_deg: rotation about the plane's up direction (degrees). fraction: instead of a
    pixel, the point (u / width, v / height) of whatever image size the session has (a
    built-in scene serves every size); used when pixel is None."""

    pixel: tuple[float, float] | None = None
    yaw_deg: float = 0.0
    fraction: tuple[float, float] | None = None

    def pixel_in(self, camera) -> tuple[float, float]:
        """(u, v) in pixels of `camera`'s image (width, height, cx, cy)."""
        if self.pixel is not None:
            return self.pixel
        if self.fraction is not None:
            return self.fraction[0] * camera.width, self.fraction[1] * camera.height
        return camera.cx, camera.cy


@dataclass(frozen=True)
class VirtualObject:
    """One mesh. vertices (N, 3) float32, object frame, metres; triangles (M, 3) int32;
    normals (N, 3) float32 unit vertex normals (smooth shading; flat meshes repeat vertices);
    world_from_object (4, 4) float64 (rotation times a uniform scale, plus translation);
    anchor: when set, world_from_object is resolved on the support plane (see Anchor)."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    world_from_object: np.ndarray
    material: Material = Material()
    anchor: Anchor | None = None

    def __post_init__(self) -> None:
        check_object(self)

    def placed(self, world_from_object: np.ndarray) -> VirtualObject:
        """The same object at a resolved pose (anchor cleared)."""
        return dataclasses.replace(
            self, world_from_object=np.asarray(world_from_object, np.float64), anchor=None
        )

    def world_vertices(self) -> np.ndarray:
        """(N, 3) float64 vertices in the world frame."""
        m = self.world_from_object
        return self.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3]

    def world_normals(self) -> np.ndarray:
        """(N, 3) float64 unit vertex normals in the world frame."""
        n = self.normals.astype(np.float64) @ np.linalg.inv(self.world_from_object[:3, :3])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """(centre (3,), radius) in the world frame, metres."""
        v = self.world_vertices()
        lo, hi = v.min(axis=0), v.max(axis=0)
        centre = 0.5 * (lo + hi)
        return centre, float(np.linalg.norm(v - centre, axis=1).max())


def check_object(obj: VirtualObject) -> None:
    """SceneError naming the object when its arrays or pose cannot be rendered."""
    where = f"virtual object {obj.name!r}"
    v, t, n = obj.vertices, obj.triangles, obj.normals
    if not (isinstance(v, np.ndarray) and v.ndim == 2 and v.shape[1] == 3 and len(v) >= 3):
        raise SceneError(
            f"{where}: vertices must be (N >= 3, 3), got {getattr(v, 'shape', type(v).__name__)}"
        )
    if not (isinstance(t, np.ndarray) and t.ndim == 2 and t.shape[1] == 3 and len(t) >= 1):
        raise SceneError(
            f"{where}: triangles must be (M >= 1, 3), got {getattr(t, 'shape', type(t).__name__)}"
        )
    if not (isinstance(n, np.ndarray) and n.shape == v.shape):
        raise SceneError(
            f"{where}: normals must match the vertices {v.shape}, got "
            f"{getattr(n, 'shape', type(n).__name__)}"
        )
    if len(t) > MAX_TRIANGLES:
        raise SceneError(
            f"{where}: {len(t)} triangles, at most {MAX_TRIANGLES} per scene; simplify the mesh"
        )
    if not np.all(np.isfinite(v)) or not np.all(np.isfinite(n)):
        raise SceneError(f"{where}: vertices or normals are not all finite")
    if t.min() < 0 or t.max() >= len(v):
        raise SceneError(f"{where}: triangle indices must lie in 0..{len(v) - 1}")
    m = np.asarray(obj.world_from_object, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise SceneError(f"{where}: world_from_object must be a finite 4x4 matrix")
    scale = float(np.cbrt(np.linalg.det(m[:3, :3]))) if np.linalg.det(m[:3, :3]) > 0 else 0.0
    if not scale > 0.0:
        raise SceneError(f"{where}: world_from_object has no positive scale (det <= 0)")
    try:
        rigid = np.eye(4)
        rigid[:3, :3], rigid[:3, 3], rigid[3] = m[:3, :3] / scale, m[:3, 3], m[3]
        check_rigid(rigid, f"{where} world_from_object / scale")
    except CheckError as exc:
        raise SceneError(
            f"{where}: world_from_object must be a rotation times one uniform "
            f"scale plus a translation ({exc})"
        ) from None
    albedo = np.asarray(obj.material.albedo, dtype=np.float64)
    if albedo.shape != (3,) or not np.all((albedo >= 0.0) & (albedo <= 1.0)):
        raise SceneError(
            f"{where}: albedo must be 3 linear RGB values in [0, 1], got {obj.material.albedo}"
        )


@dataclass(frozen=True)
class VirtualScene:
    """The virtual objects of one session; empty: nothing to render (the composite is the
    input frame, and the Rendering stage costs nothing)."""

    objects: tuple[VirtualObject, ...] = ()

    def __post_init__(self) -> None:
        if len(self.objects) > MAX_OBJECTS:
            raise SceneError(f"{len(self.objects)} virtual objects, at most {MAX_OBJECTS}")
        total = sum(len(o.triangles) for o in self.objects)
        if total > MAX_TRIANGLES:
            raise SceneError(
                f"the virtual scene has {total} triangles, at most "
                f"{MAX_TRIANGLES}; simplify its meshes"
            )
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise SceneError(f"virtual object names must be unique, got {names}")

    @property
    def anchored(self) -> bool:
        """True while some object still waits for a support plane to stand on."""
        return any(o.anchor is not None for o in self.objects)

    def __bool__(self) -> bool:
        return bool(self.objects)


def object_from_open3d(
    name: str,
    mesh: o3d.geometry.TriangleMesh,
    world_from_object: np.ndarray,
    material: Material = Material(),
    anchor: Anchor | None = None,
) -> VirtualObject:
    """A VirtualObject from an Open3D legacy mesh (vertex normals computed when missing)."""
    if not mesh.has_vertex_normals():
        mesh.compute_vertex_normals()
    return VirtualObject(
        name,
        np.asarray(mesh.vertices, np.float32),
        np.asarray(mesh.triangles, np.int32),
        np.asarray(mesh.vertex_normals, np.float32),
        np.asarray(world_from_object, np.float64),
        material,
        anchor,
    )


def _standing(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """The mesh translated so that its lowest point is at y = 0 above the origin."""
    lo = np.asarray(mesh.vertices).min(axis=0)
    hi = np.asarray(mesh.vertices).max(axis=0)
    return mesh.translate((-(lo[0] + hi[0]) / 2, -lo[1], -(lo[2] + hi[2]) / 2))


def sphere_mesh(radius_m: float = 0.1, resolution: int = 24) -> o3d.geometry.TriangleMesh:
    """A UV sphere standing on the origin (object frame: base centre, +y up)."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius_m, resolution=resolution)
    mesh.compute_vertex_normals()
    return _standing(mesh)


def box_mesh(size_m: tuple[float, float, float] = (0.2, 0.2, 0.2)) -> o3d.geometry.TriangleMesh:
    """A box (width x, height y, depth z) standing on the origin, flat faces."""
    mesh = o3d.geometry.TriangleMesh.create_box(*size_m)
    mesh = _flat(mesh)
    return _standing(mesh)


def torus_mesh(
    ring_radius_m: float = 0.1, tube_radius_m: float = 0.035, resolution: int = 40
) -> o3d.geometry.TriangleMesh:
    """A torus standing upright on the origin (ring in the x-y plane), smooth normals: a
    non-convex object that shadows itself and shows the ground through its hole."""
    mesh = o3d.geometry.TriangleMesh.create_torus(
        ring_radius_m, tube_radius_m, resolution, max(12, resolution // 2)
    )
    # Open3D makes the ring in the x-y plane already; stand it up on its rim
    mesh.compute_vertex_normals()
    return _standing(mesh)


def _flat(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """Every triangle with its own vertices and its face normal (flat shading)."""
    v = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].reshape(-1, 3)
    out = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(np.arange(len(v)).reshape(-1, 3))
    )
    out.compute_triangle_normals()
    face = np.asarray(out.triangle_normals)
    out.vertex_normals = o3d.utility.Vector3dVector(np.repeat(face, 3, axis=0))
    return out


# name -> the function making it (its keyword arguments: the primitive's sizes)
PRIMITIVES: dict[str, Callable[..., o3d.geometry.TriangleMesh]] = {
    "sphere": sphere_mesh,
    "box": box_mesh,
    "torus": torus_mesh,
}


def pose_on_plane(
    point_world: np.ndarray,
    up_world: np.ndarray,
    yaw_deg: float = 0.0,
    forward_world: np.ndarray | None = None,
) -> np.ndarray:
    """world_from_object standing at `point_world` with object +y along `up_world`, object
    +z along the horizontal part of `forward_world` (default: any), turned by yaw_deg."""
    up = np.asarray(up_world, np.float64)
    up = up / np.linalg.norm(up)
    f = np.asarray(forward_world if forward_world is not None else [0.0, 0.0, 1.0], np.float64)
    f = f - (f @ up) * up
    if np.linalg.norm(f) < 1e-6:
        f = np.array([1.0, 0.0, 0.0]) - up[0] * up
    z = f / np.linalg.norm(f)
    x = np.cross(up, z)
    yaw = np.radians(yaw_deg)
    x, z = np.cos(yaw) * x - np.sin(yaw) * z, np.sin(yaw) * x + np.cos(yaw) * z
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, up, z, point_world
    return m


def resolve_anchors(
    scene: VirtualScene, up_cam: np.ndarray, offset_m: float, world_from_cam: np.ndarray, camera
) -> VirtualScene:
    """Anchored objects placed on the plane up . p + offset = 0 (camera frame) under their
    pixel; objects whose ray misses the plane (it points above the horizon) stay anchored."""
    out = []
    rot, trans = world_from_cam[:3, :3], world_from_cam[:3, 3]
    up_cam = np.asarray(up_cam, np.float64)
    for obj in scene.objects:
        if obj.anchor is None:
            out.append(obj)
            continue
        u, v = obj.anchor.pixel_in(camera)
        ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        denom = float(up_cam @ ray)
        t = -offset_m / denom if abs(denom) > 1e-9 else -1.0
        if not t > 0.0:
            out.append(obj)
            continue
        point = rot @ (t * ray) + trans
        # the object faces the camera: its +z towards the camera, horizontally
        toward_camera = trans - point
        out.append(
            obj.placed(
                pose_on_plane(point, rot @ up_cam, obj.anchor.yaw_deg, toward_camera)
                @ np.diag([*[_scale(obj)] * 3, 1.0])
            )
        )
    return VirtualScene(tuple(out))


def _scale(obj: VirtualObject) -> float:
    """The uniform scale carried by an object's world_from_object."""
    return float(np.cbrt(np.linalg.det(obj.world_from_object[:3, :3])))


def demo_scene(image_size: tuple[int, int] | None = None) -> VirtualScene:
    """The demo's objects: a chrome sphere (a mirror: it reflects the room through the
    reflection probe, pipeline/probe.py) and an upright orange torus (non-convex), anchored
    on the support plane left and right of the view's centre, a little below it: at the
    same fractions of any image (None, what a server's session uses: 160x120 to 1280x720
    alike), or at those pixels of an image of image_size (width, height)."""
    at = [(0.39, 0.69), (0.625, 0.69)]  # (u / width, v / height) of the sphere and torus

    def anchor(i: int, yaw_deg: float = 0.0) -> Anchor:
        if image_size is None:
            return Anchor(None, yaw_deg, fraction=at[i])
        return Anchor((at[i][0] * image_size[0], at[i][1] * image_size[1]), yaw_deg)

    sphere = object_from_open3d(
        "sphere", sphere_mesh(0.12), np.eye(4), Material((0.9, 0.9, 0.9), mirror=True), anchor(0)
    )
    torus = object_from_open3d(
        "torus",
        torus_mesh(0.1, 0.035),
        np.eye(4),
        Material((0.8, 0.3, 0.08)),
        anchor(1, yaw_deg=30.0),
    )
    return VirtualScene((sphere, torus))
