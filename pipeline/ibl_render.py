"""Virtual objects lit by an HDR panorama, rendered into a perspective view cut from it (the
360 paper's Algorithm 1 and section 5; mono and a stereo pair for head-mounted displays).

World frame = the panorama's frame (``pipeline/equirect.py``: +y up; metres for the objects),
the panorama at infinity. A view is a pinhole camera (OpenCV axes: x right, y down, z
forward) at `world_from_cam`; by default at the origin looking along a chosen direction
(:func:`look_along`). Per pixel of a view:

- background: the LDR panorama resampled into the view (bilinear, the panorama's own 8-bit
  sRGB values; HDR inputs: their sRGB encoding at `exposure`);
- virtual objects (the G-buffer of ``virtual_gbuffer.VirtualRaycaster``, Open3D ray casting,
  the same as the AR path's): normal n (world), view direction v, mirror direction
  r = v - 2 (n . v) n, and the radiance
      L = diffuse_rgb * E(n) / pi + specular_rgb * S(r)
  with E the irradiance of the frame's diffuse map (``pipeline/ibl.py``, bilinear lookup by
  the normal) and S the mirror (one level-0 lookup) or glossy (``pipeline/glossy.py``) lookup
  of the HDR map's mip pyramid; composited as sRGB(clip(exposure L)). On the CPU the glossy
  lobes of each roughness are evaluated once per frame on a small map and looked up per
  pixel (``pipeline/glossy_prefilter.py``) where that costs less than per pixel; the pyramid
  is made only when a mirror or glossy object is in view.

Material fields -> shading (:func:`shading_of`):
- specular weight s = 1 when `mirror`, else `metalness`;
- diffuse_rgb = (1 - s) albedo (Lambertian), specular_rgb = s albedo (a metal's tinted
  reflection; no Fresnel term);
- the specular lobe: `mirror` -> a single lookup at level 0; otherwise, when s > 0, a glossy
  Phong lobe of the object's `roughness`, which must then lie in 0.01..0.5 (the paper's fig.
  6 range); s = 0: diffuse only, roughness unused.

Exposure 1 composites the HDR map at the scale of the LDR it came from: the default `boost`
operator keeps unclipped pixels at their decoded sRGB values, so a mirror shows the
background as it is.

Stereo (:func:`eye_poses`): two views 64 mm apart (the interpupillary distance) along the
camera's x axis, each 1182 x 1464 by default (the paper's Oculus DK2 per eye), written side
by side (left eye on the left).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.pipeline import equirect, glossy, glossy_prefilter
from arlight.pipeline.rendering import linear_to_srgb_u8
from arlight.pipeline.virtual_gbuffer import VirtualRaycaster
from arlight.pipeline.virtual_scene import (
    Material,
    SceneError,
    VirtualScene,
    object_from_open3d,
    pose_on_plane,
    sphere_mesh,
    torus_mesh,
)

MONO_SIZE = (1280, 720)  # the paper's single camera view
EYE_SIZE = (1182, 1464)  # per eye, the paper's Oculus DK2
IPD_M = 0.064  # interpupillary distance
MODE_NONE, MODE_MIRROR, MODE_GLOSSY = 0, 1, 2
DEMO_ROUGHNESS = (0.1, 0.3)  # the demo's two glossy spheres


@dataclass(frozen=True)
class Shading:
    """What the renderer does with one Material (see the module text)."""

    diffuse_rgb: np.ndarray  # (3,)
    specular_rgb: np.ndarray  # (3,)
    mode: int  # MODE_NONE / MODE_MIRROR / MODE_GLOSSY
    exponent: float  # Phong exponent (glossy only, else 0)


def shading_of(material: Material, where: str = "material") -> Shading:
    """The Shading of a Material; SceneError naming `where` for a glossy lobe whose roughness
    lies outside 0.01..0.5."""
    albedo = np.asarray(material.albedo, np.float64)
    s = 1.0 if material.mirror else float(material.metalness)
    if material.mirror:
        mode, exponent = MODE_MIRROR, 0.0
    elif s > 0.0:
        try:
            exponent = glossy.phong_exponent(material.roughness)
        except ValueError:
            raise SceneError(
                f"{where}: roughness must be in [{glossy.ROUGHNESS_MIN}, "
                f"{glossy.ROUGHNESS_MAX}] for a glossy object (metalness {s:g} > 0, not a "
                f"mirror), got {material.roughness:g}"
            ) from None
        mode = MODE_GLOSSY
    else:
        mode, exponent = MODE_NONE, 0.0
    return Shading((1.0 - s) * albedo, s * albedo, mode, exponent)


def view_camera(size: tuple[int, int], hfov_deg: float) -> PinholeCamera:
    """A centred pinhole camera of `size` (width, height) pixels, horizontal field of view
    `hfov_deg` degrees (square pixels)."""
    w, h = int(size[0]), int(size[1])
    if not 1.0 <= hfov_deg <= 170.0:
        raise ValueError(f"hfov_deg must be in [1, 170] degrees, got {hfov_deg}")
    f = 0.5 * w / math.tan(math.radians(hfov_deg) / 2.0)
    return PinholeCamera(w, h, f, f, (w - 1) / 2.0, (h - 1) / 2.0)


def direction_of(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit direction at `elevation_deg` above the horizon and `azimuth_deg` from -z towards
    +x: it shows at the panorama's column u = azimuth / 360 (180 = the centre column, +z)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)])


def look_along(forward: np.ndarray, position: np.ndarray | None = None) -> np.ndarray:
    """world_from_cam (4x4) of a camera at `position` (default the origin) whose optical axis
    (+z) is `forward` and whose image up (-y) is as close to world +y as it can be."""
    z = np.asarray(forward, np.float64)
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.999 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, up)  # right: z x up (OpenCV: x = y x z with y = -up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, y, z
    if position is not None:
        m[:3, 3] = position
    return m


def eye_poses(world_from_cam: np.ndarray, ipd_m: float = IPD_M) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) world_from_eye: the head pose moved by -/+ ipd / 2 along its x axis."""
    left, right = world_from_cam.copy(), world_from_cam.copy()
    left[:3, 3] -= 0.5 * ipd_m * world_from_cam[:3, 0]
    right[:3, 3] += 0.5 * ipd_m * world_from_cam[:3, 0]
    return left, right


def demo_scene(
    forward: np.ndarray | None = None, roughness: tuple[float, float] = DEMO_ROUGHNESS
) -> VirtualScene:
    """The built-in 5 objects (as the paper shows five at once), 1.6 m in front of a camera
    at the origin looking along `forward` (default +z, the panorama's centre column), left to
    right: diffuse sphere, glossy sphere (roughness[0], default 0.1), mirror sphere, glossy
    sphere (roughness[1], default 0.3), and a torus mesh half diffuse, half glossy (roughness
    0.2). Roughness outside 0.01..0.5: ValueError."""
    r1, r2 = (glossy.check_roughness(r, "demo roughness") for r in roughness)
    f = np.asarray(forward if forward is not None else [0.0, 0.0, 1.0], np.float64)
    f = f / np.linalg.norm(f)
    cam = look_along(f)
    right, down = cam[:3, 0], cam[:3, 1]
    specs = [
        ("diffuse", sphere_mesh(0.14, 48), Material((0.8, 0.8, 0.8))),
        ("glossy_1", sphere_mesh(0.14, 48), Material((0.95, 0.8, 0.45), r1, 1.0)),
        ("mirror", sphere_mesh(0.14, 48), Material((0.95, 0.95, 0.95), mirror=True)),
        ("glossy_2", sphere_mesh(0.14, 48), Material((0.9, 0.9, 0.9), r2, 1.0)),
        ("torus", torus_mesh(0.12, 0.045, 64), Material((0.8, 0.3, 0.1), 0.2, 0.5)),
    ]
    objects = []
    for i, (name, mesh, material) in enumerate(specs):
        base = 1.6 * f + (i - 2) * 0.36 * right + 0.14 * down  # spheres centred on the axis
        # object +y along world up through the view's down axis, facing the camera
        pose = pose_on_plane(base, -down, 0.0, -f)
        objects.append(object_from_open3d(name, mesh, pose, material))
    return VirtualScene(tuple(objects))


@dataclass
class ViewBuffers:
    """What a view needs per frame, made once per (scene, camera, pose).

    pixels: (K,) flat indices of the pixels that show a virtual object; normals,
    mirror_dirs: (K, 3) float64 world unit normals (facing the camera) and mirror directions
    of the view rays; the shading tables gathered per pixel; uv: (H, W, 2) float32 panorama
    coordinates of every pixel's ray (for the background); gbuffer_ms: the ray cast's time.
    """

    camera: PinholeCamera
    pixels: np.ndarray
    normals: np.ndarray
    mirror_dirs: np.ndarray
    diffuse_rgb: np.ndarray
    specular_rgb: np.ndarray
    modes: np.ndarray
    exponents: np.ndarray
    uv: np.ndarray
    gbuffer_ms: float
    _remap: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    def remap_maps(self, height: int) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) (H, W) float32 source pixel coordinates of every pixel's ray in a panorama
        of `height` rows (2 height columns; pixel centres at integers, rows clamped to the
        map), made once per panorama size."""
        if height not in self._remap:
            x = self.uv[..., 0] * np.float32(2 * height) - np.float32(0.5)
            y = np.clip(self.uv[..., 1] * np.float32(height) - np.float32(0.5), 0, height - 1)
            self._remap[height] = (x.astype(np.float32), y.astype(np.float32))
        return self._remap[height]


class FrameLight:
    """One frame's lighting for the renderer: the LDR panorama (for the background; None for
    HDR input), the HDR map, its diffuse (irradiance) map, and what the glossy and mirror
    lookups need, made on first use (a scene of diffuse objects needs neither): the mip
    pyramid and the prefiltered glossy maps (``glossy_prefilter``). Not thread-safe."""

    def __init__(
        self,
        hdr: np.ndarray,
        diffuse_map: np.ndarray,
        ldr: np.ndarray | None = None,
        exposure: float = 1.0,
        pyramid_buffer: np.ndarray | None = None,
    ):
        """pyramid_buffer: where to build the pyramid (``glossy.mip_pyramid``'s buffer; the
        caller's, reused frame after frame), or None for a new array."""
        self.hdr = hdr
        self._buffer = pyramid_buffer
        self.ldr = ldr
        self.diffuse_map = np.asarray(diffuse_map, np.float32)
        self.exposure = exposure
        self.pyramid_ms = 0.0
        self._pyramid: glossy.MipPyramid | None = None
        self._level0: np.ndarray | None = None
        self._maps: glossy_prefilter.PrefilteredMaps | None = None

    @property
    def pyramid(self) -> glossy.MipPyramid:
        """The HDR map's mip pyramid (``glossy.mip_pyramid``), made once."""
        if self._pyramid is None:
            t0 = time.perf_counter()
            self._pyramid = glossy.mip_pyramid(self.hdr, self._buffer)
            self.pyramid_ms = (time.perf_counter() - t0) * 1e3
        return self._pyramid

    @property
    def level0(self) -> np.ndarray:
        """(H, W, 3) float32 C-contiguous: the pyramid's level 0 (the map, non-finite or
        negative radiance as 0), without building the other levels where none is built."""
        if self._pyramid is not None:
            return self._pyramid.levels[0]
        if self._level0 is None:
            a = np.ascontiguousarray(self.hdr, dtype=np.float32)
            if not np.all(np.isfinite(a)) or a.min() < 0.0:
                a = np.maximum(np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
            self._level0 = a
        return self._level0

    @property
    def prefiltered(self) -> glossy_prefilter.PrefilteredMaps:
        """The prefiltered glossy maps of the pyramid, each made on first use."""
        if self._maps is None:
            self._maps = glossy_prefilter.PrefilteredMaps(self.pyramid)
        return self._maps

    @property
    def prefilter_ms(self) -> float:
        return 0.0 if self._maps is None else self._maps.prefilter_ms


@dataclass
class RenderOutput:
    """rgb: (H, W, 3) uint8 sRGB composite; radiance: (H, W, 3) float32 linear radiance of
    the virtual objects (0 elsewhere); mask: (H, W) bool, the objects' pixels."""

    rgb: np.ndarray
    radiance: np.ndarray
    mask: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)


def frame_light(
    hdr: np.ndarray,
    diffuse_map: np.ndarray,
    ldr: np.ndarray | None = None,
    exposure: float = 1.0,
    pyramid_buffer: np.ndarray | None = None,
) -> FrameLight:
    """The per-frame lighting of an HDR map (H, W, 3) linear; its pyramid is made when a
    mirror or glossy object first needs it (in `pyramid_buffer` where given)."""
    return FrameLight(hdr, diffuse_map, ldr, exposure, pyramid_buffer)


class IblRenderer:
    """Renders one virtual scene (panorama frame) lit by panorama frames (not thread-safe)."""

    def __init__(self, scene: VirtualScene, backend: str = "cpu"):
        """backend: "cpu" or "cuda" for the mirror / glossy lookups (``glossy.specular``; the
        same per-pixel code on both; "cuda" without a visible GPU raises RuntimeError)."""
        if backend not in glossy.BACKENDS:
            raise ValueError(f"backend must be one of {glossy.BACKENDS}, got {backend!r}")
        if backend == "cuda" and not glossy.cuda_available():
            raise RuntimeError(
                "backend='cuda' requested but numba.cuda sees no GPU; use backend='cpu'"
            )
        self.backend = backend
        for o in scene.objects:
            if o.anchor is not None:
                raise SceneError(
                    f"virtual object {o.name!r}: an anchor needs a support plane, "
                    "which a panorama does not give; pose it with "
                    "world_from_object (the panorama's frame, +y up, metres, the "
                    "camera at the origin)"
                )
        shadings = [shading_of(o.material, f"virtual object {o.name!r}") for o in scene.objects]
        self.scene = scene
        self._raycaster = VirtualRaycaster(scene)
        n = max(1, len(shadings))
        self._diffuse = np.zeros((n, 3))
        self._specular = np.zeros((n, 3))
        self._modes = np.zeros(n, np.int64)
        self._exponents = np.zeros(n)
        for i, s in enumerate(shadings):
            self._diffuse[i], self._specular[i] = s.diffuse_rgb, s.specular_rgb
            self._modes[i], self._exponents[i] = s.mode, s.exponent

    def prepare_view(self, camera: PinholeCamera, world_from_cam: np.ndarray) -> ViewBuffers:
        """The G-buffer of the objects and the background's panorama coordinates of a view."""
        t0 = time.perf_counter()
        gb = self._raycaster.camera_gbuffer(camera, world_from_cam)
        gbuffer_ms = (time.perf_counter() - t0) * 1e3
        rot = world_from_cam[:3, :3]
        rays_world = camera.ray_directions().astype(np.float64) @ rot.T  # (H, W, 3) unit
        u, v = equirect.uv_of(rays_world)
        uv = np.stack([u, v], axis=-1).astype(np.float32)
        pixels = np.flatnonzero(gb.hit.reshape(-1))
        obj = gb.object_index.reshape(-1)[pixels]
        normals = gb.normals_cam.reshape(-1, 3)[pixels].astype(np.float64) @ rot.T
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        views = rays_world.reshape(-1, 3)[pixels]
        mirror_dirs = views - 2.0 * np.einsum("ij,ij->i", normals, views)[:, None] * normals
        return ViewBuffers(
            camera,
            pixels,
            normals,
            np.ascontiguousarray(mirror_dirs),
            self._diffuse[obj],
            self._specular[obj],
            self._modes[obj],
            self._exponents[obj],
            uv,
            gbuffer_ms,
        )

    def render(self, view: ViewBuffers, light: FrameLight) -> RenderOutput:
        """One view of one frame: background, then the objects' shading."""
        t0 = time.perf_counter()
        cam = view.camera
        background = _background(view, light)
        t1 = time.perf_counter()
        radiance = np.zeros((cam.height * cam.width, 3), np.float32)
        if len(view.pixels):
            irradiance = glossy.lookup(light.diffuse_map, view.normals)
            spec = self._reflection(view, light)
            radiance[view.pixels] = (
                view.diffuse_rgb * irradiance * (1.0 / math.pi) + view.specular_rgb * spec
            )
        t2 = time.perf_counter()
        rgb = background.reshape(-1, 3)
        if len(view.pixels):
            rgb[view.pixels] = linear_to_srgb_u8(radiance[view.pixels] * light.exposure)
        mask = np.zeros(cam.height * cam.width, bool)
        mask[view.pixels] = True
        t3 = time.perf_counter()
        return RenderOutput(
            rgb.reshape(cam.height, cam.width, 3),
            radiance.reshape(cam.height, cam.width, 3),
            mask.reshape(cam.height, cam.width),
            {
                "Background": (t1 - t0) * 1e3,
                "Shading": (t2 - t1) * 1e3,
                "Composite": (t3 - t2) * 1e3,
            },
        )

    def _reflection(self, view: ViewBuffers, light: FrameLight) -> np.ndarray:
        """(K, 3) float32 mirror / glossy radiance of the view's object pixels: no pyramid
        where no pixel reflects; on the CPU the glossy lobes through the prefiltered maps
        (``glossy_prefilter.specular``), on "cuda" every lobe per pixel."""
        if not np.any(view.modes != MODE_NONE):
            return np.zeros((len(view.pixels), 3), np.float32)
        if self.backend == "cpu" and not np.any(view.modes == MODE_GLOSSY):
            # mirrors only: one lookup in level 0, the map itself; no pyramid to build
            out = np.zeros((len(view.pixels), 3), np.float32)
            rows = np.flatnonzero(view.modes == MODE_MIRROR)
            glossy_prefilter.lookup_rows(light.level0, view.mirror_dirs, rows, out)
            return out
        if self.backend == "cuda":
            return glossy.specular(
                light.pyramid, view.mirror_dirs, view.modes, view.exponents, self.backend
            )
        return glossy_prefilter.specular(
            light.prefiltered, view.mirror_dirs, view.modes, view.exponents
        )


def _background(view: ViewBuffers, light: FrameLight) -> np.ndarray:
    """(H, W, 3) uint8: the panorama resampled at every pixel's (u, v) (bilinear, u wrapped,
    rows clamped at the poles)."""
    if light.ldr is not None:
        src = np.ascontiguousarray(light.ldr, dtype=np.uint8)
    else:
        hdr = np.asarray(light.hdr, np.float32)
        src = linear_to_srgb_u8(np.nan_to_num(hdr, nan=0.0, posinf=0.0) * light.exposure)
    x, y = view.remap_maps(src.shape[0])
    # x wraps at the seam (BORDER_WRAP); y is clamped in the map, so no row wraps
    return cv2.remap(src, x, y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The stereo pair as one image, left eye on the left."""
    return np.concatenate([left, right], axis=1)
