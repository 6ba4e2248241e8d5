"""Path tracing with Mitsuba 3 (the ``synth`` extra; the only module that imports it) and
ray casting with Open3D (clean depth, masks), over the same triangle meshes.

Mitsuba's ``scalar_rgb`` variant, path tracer, an ``envmap`` emitter rotated about +Y,
Lambertian surfaces (two-sided) and, for virtual objects, GGX ``principled`` or a perfect
``conductor`` mirror. Cameras: Mitsuba's perspective camera has x left, y up; arlight's
world_from_cam has OpenCV axes, so ``to_world = world_from_cam @ diag(-1, -1, 1, 1)``. The
principal point is the image centre ((W - 1) / 2, (H - 1) / 2: OpenCV pixel centres), which
is Mitsuba's film centre. Images are (H, W, 3) float32 linear radiance in the map's units.
"""

from __future__ import annotations

import functools
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from arlight.synth.layouts import Shape
from arlight.synth.materials import Material
from arlight.synth.meshes import write_ply

VARIANT = "scalar_rgb"  # the shared set's; the LLVM variants need a matching system libLLVM
FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV camera axes -> Mitsuba's (x left, y up)
MAX_DEPTH_M = 65535 / 5000  # beyond the 16-bit depth encoding: 0 in depth_gt


class MissingExtra(RuntimeError):
    """Mitsuba is not installed."""


def mitsuba():
    """The mitsuba module with the generator's variant set; a clear error when absent."""
    try:
        import mitsuba as mi
    except ImportError:
        raise MissingExtra(
            "arlight synth needs Mitsuba 3: pip install 'arlight[synth]' (or "
            ".venv/bin/pip install mitsuba)"
        ) from None
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


def version() -> str:
    return mitsuba().__version__


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels, principal point at the image centre."""

    width: int
    height: int
    fx: float
    fy: float

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2

    def rays_camera(self) -> np.ndarray:
        """(H, W, 3) ray directions through the pixel centres with z = 1 (OpenCV)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], -1)


def _bsdf(mi, material: Material, texture_cache: dict) -> dict:
    if material.mirror:
        return {
            "type": "conductor",
            "material": "none",
            "specular_reflectance": {"type": "rgb", "value": list(material.albedo_rgb)},
        }
    if material.textured:
        key = (material.kind, material.seed, material.colours)
        if key not in texture_cache:
            texture_cache[key] = mi.Bitmap(material.texture())
        reflectance = {
            "type": "bitmap",
            "bitmap": texture_cache[key],
            "raw": True,
            "filter_type": "bilinear",
            "wrap_mode": "repeat",
            "to_uv": mi.ScalarTransform4f().scale([material.repeats, material.repeats, 1]),
        }
    else:
        reflectance = {"type": "rgb", "value": list(material.albedo_rgb)}
    if material.roughness is not None:
        return {
            "type": "principled",
            "base_color": reflectance,
            "roughness": float(material.roughness),
            "metallic": float(material.metalness),
        }
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}}


def _environment(mi, map_path: Path, rotation_deg: float) -> dict:
    return {
        "type": "envmap",
        "filename": str(map_path),
        "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], rotation_deg),
    }


class SceneRenderer:
    """Renders one scene state (shapes + one rotated map) from any camera pose."""

    def __init__(
        self, shapes: list[Shape], map_path: Path, rotation_deg: float, max_depth: int = 4
    ):
        self._mi = mi = mitsuba()
        self._tmp = tempfile.TemporaryDirectory(prefix="arlight-synth-")
        cache: dict = {}
        self._objects: dict = {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": int(max_depth)},
            "environment": _environment(mi, map_path, rotation_deg),
        }
        for k, shape in enumerate(shapes):
            ply = Path(self._tmp.name) / f"{k:03d}.ply"
            write_ply(shape.mesh(), ply)
            self._objects[f"s{k:03d}_{shape.name}"] = {
                "type": "ply",
                "filename": str(ply),
                "face_normals": False,
                "bsdf": _bsdf(mi, shape.material, cache),
            }
        self._scene = mi.load_dict(self._objects)
        self._albedo_scene = None  # the same scene under Mitsuba's aov integrator (on first use)

    def close(self) -> None:
        self._tmp.cleanup()

    def render(
        self,
        camera: Camera,
        world_from_cam: np.ndarray,
        spp: int,
        seed: int,
        rfilter: str = "gaussian",
    ) -> np.ndarray:
        """(H, W, 3) float32 linear radiance seen through `camera` at `world_from_cam`."""
        sensor = self._sensor(camera, world_from_cam, spp, rfilter)
        image = self._mi.render(self._scene, sensor=sensor, seed=int(seed), spp=int(spp))
        return np.asarray(image, np.float32)[..., :3]

    def render_albedo(
        self, camera: Camera, world_from_cam: np.ndarray, seed: int, spp: int = 4
    ) -> np.ndarray:
        """(H, W, 3) float32 linear albedo (diffuse reflectance, 0..1) of the first surface
        each pixel sees, averaged over its footprint (box filter): the intrinsic image the
        estimate's per-material albedos stand for; 0 where the pixel sees the environment."""
        mi = self._mi
        if self._albedo_scene is None:
            objects = dict(self._objects)
            objects["integrator"] = {"type": "aov", "aovs": "albedo:albedo"}
            self._albedo_scene = mi.load_dict(objects)
        sensor = self._sensor(camera, world_from_cam, spp, "box")
        image = mi.render(self._albedo_scene, sensor=sensor, seed=int(seed), spp=int(spp))
        return np.asarray(image, np.float32)[..., :3]

    def _sensor(self, camera: Camera, world_from_cam: np.ndarray, spp: int, rfilter: str):
        """Mitsuba's perspective sensor for `camera` at `world_from_cam` (OpenCV axes)."""
        mi = self._mi
        fov = math.degrees(2 * math.atan(camera.height / 2 / camera.fy))
        aspect_ok = abs(camera.fx - camera.fy) < 1e-9
        if not aspect_ok:
            raise ValueError("the generator's cameras have square pixels (fx == fy)")
        return mi.load_dict(
            {
                "type": "perspective",
                "fov": fov,
                "fov_axis": "y",
                "to_world": mi.ScalarTransform4f(np.asarray(world_from_cam, float) @ FLIP),
                "film": {
                    "type": "hdrfilm",
                    "width": camera.width,
                    "height": camera.height,
                    "rfilter": {"type": rfilter},
                    "pixel_format": "rgb",
                },
                "sampler": {"type": "independent", "sample_count": int(spp)},
            }
        )


# --------------------------------------------------------------------------- ray casting


class GeometryCaster:
    """Open3D ray casting against the shapes' meshes: clean depth and which shape is hit."""

    def __init__(self, shapes: list[Shape]):
        import open3d as o3d

        self._scene = o3d.t.geometry.RaycastingScene()
        self.names: list[str] = []
        for shape in shapes:
            mesh = shape.mesh()
            self._scene.add_triangles(
                o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                o3d.core.Tensor(mesh.faces.astype(np.uint32)),
            )
            self.names.append(shape.name)

    def cast(self, camera: Camera, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """depth (H, W) float32 camera z in metres (0 = nothing within MAX_DEPTH_M) and the
        index (H, W) int32 into `names` of the first surface hit (-1 = environment)."""
        import open3d as o3d

        pose = np.asarray(world_from_cam, float)
        dirs = camera.rays_camera().reshape(-1, 3) @ pose[:3, :3].T
        rays = np.concatenate([np.broadcast_to(pose[:3, 3], dirs.shape), dirs], 1)
        hit = self._scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        t = hit["t_hit"].numpy().reshape(camera.height, camera.width)
        ids = hit["geometry_ids"].numpy().astype(np.int64).reshape(camera.height, camera.width)
        ok = np.isfinite(t) & (t <= MAX_DEPTH_M)
        return np.where(ok, t, 0).astype(np.float32), np.where(np.isfinite(t), ids, -1).astype(
            np.int32
        )


# --------------------------------------------------------------------------- probes

CUBE_FACES = {  # face name -> (forward, down) in the world frame, OpenCV camera axes
    "px": ((1, 0, 0), (0, -1, 0)),
    "nx": ((-1, 0, 0), (0, -1, 0)),
    "py": ((0, 1, 0), (0, 0, 1)),
    "ny": ((0, -1, 0), (0, 0, -1)),
    "pz": ((0, 0, 1), (0, -1, 0)),
    "nz": ((0, 0, -1), (0, -1, 0)),
}


def cube_face_pose(face: str, point) -> np.ndarray:
    forward, down = (np.asarray(v, float) for v in CUBE_FACES[face])
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = np.cross(down, forward), down, forward
    pose[:3, 3] = point
    return pose


@functools.lru_cache(maxsize=4)
def cube_texels(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per face (6, S, S, 3) unit world directions of texel centres (faces in CUBE_FACES
    order) and (S, S) texel solid angles (steradians; the six faces tile the sphere)."""
    cam = Camera(size, size, size / 2, size / 2)
    rays = cam.rays_camera()
    norm = np.linalg.norm(rays, axis=-1)
    dirs = []
    for face in CUBE_FACES:
        r = cube_face_pose(face, (0, 0, 0))[:3, :3]
        dirs.append((rays / norm[..., None]) @ r.T)
    # solid angle of a texel of side 2/S on the plane z = 1: dA cos / r^2 = dA / r^3
    solid = (2.0 / size) ** 2 / norm**3
    out = np.stack(dirs), solid
    for a in out:
        a.flags.writeable = False  # shared by every caller (cached)
    return out


def render_probe(renderer: SceneRenderer, point, size: int, spp: int, seed: int) -> np.ndarray:
    """(6, S, S, 3) float32 radiance arriving at `point` (world), faces in CUBE_FACES order."""
    cam = Camera(size, size, size / 2, size / 2)
    return np.stack(
        [
            renderer.render(cam, cube_face_pose(face, point), spp, seed + k, "box")
            for k, face in enumerate(CUBE_FACES)
        ]
    )
