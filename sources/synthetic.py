"""Procedural RGB-D sequence with KNOWN distant lighting: the built-in test and demo input.

Scene (world frame as in ``../shared/data/synthetic``: right-handed, metres, +Y up, ground
plane y = 0): an infinite Lambertian ground with a mild procedural texture (albedo +-15 %,
soft checker plus smooth noise, faded out from 4 to 8 m against aliasing) and four objects
standing on it within 0.55 m of the origin (:data:`SCENE_OBJECTS`: a white sphere, a small
grey sphere, a red yawed box, a tall grey box; sizes 0.16-0.36 m).

Camera: Kinect-v1 pinhole (``PinholeCamera.kinect_v1``), OpenCV axes, on an orbit of radius
2 m at 1 m height looking at (0, 0.2, 0), sweeping 75 degrees over the sequence from 70
degrees round (about +Y) from the sun's azimuth; a strip of sky shows above the horizon.
Poses are camera-to-world (``world_from_cam``), timestamps 1000 + i / 30 s.

Lighting (:class:`Lighting`), a distant environment over the WHOLE sphere of directions w:

* sky, per linear RGB channel ``L(w) = a + b_y w_y + q w_y^2 + g (w . h)`` with h the
  horizontal unit vector towards the sun: brighter towards the zenith, a little brighter on
  the sun's side, and below the horizon it falls to a dark "ground bounce" radiance at the
  nadir. A quadratic polynomial of w lies in SH bands 0..2, so its SH is exact and written in
  closed form (:meth:`Lighting.sky_sh_rgb`; tests check it against numerical projection).
* sun: a delta light from ``sun_direction`` (elevation 30-50 degrees, azimuth from the seed)
  with integrated radiance ``sun_rgb`` (the irradiance it gives a surface facing it). Its SH
  is ``sh.directional_light``; it makes ~5/6 of the first band's length, so the dominant
  direction lies between sun and zenith, 3-6 degrees from the sun.

Ground truth: ``sh_world`` is the luminance (0.2126 R + 0.7152 G + 0.0722 B) SH of that full
environment, sky (exact) + sun (delta, truncated to bands 0..3), world frame, arlight basis
(no Condon-Shortley phase), in the radiance units of the linear rendering before exposure.
The lower hemisphere is part of it (the ground-bounce sky term), as in the shared set, where
the environment map's lower half is part of the ground-truth SH.

Shading (Lambertian, no interreflection): ``albedo / pi * (sun_rgb max(0, n.s) V_sun(x) +
AO(x) E_sky(n))`` with V_sun from shadow rays against the analytic primitives (hard shadows:
the sun is a delta), E_sky the exact SH irradiance of the whole-sphere sky (the lower
hemisphere stands for light bounced off the ground, so the ground plane itself does not
occlude), and AO a cheap analytic occlusion of the sky by the objects, each seen as a sphere.

Images: one ray through every pixel centre; depth = camera-space z in metres, 0 where a ray
hits nothing (sky pixels show the sky radiance). Colour = sRGB(clip(exposure * radiance)),
with the exposure fixed per sequence so that sunlit ground of mean albedo is mid-grey (0.18
linear), plus Gaussian noise (sigma 1.5/255) before rounding to uint8 when ``sensor_noise``.
Sensor depth (``sensor_noise``): Kinect-v1-like z + N(0, sigma(z)^2) with
sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2, a one-pixel band removed along depth jumps, ~1 %
random dropouts, 0 outside 0.4-4.0 m, quantised to 1/5000 m: the frames carry those
integers, (H, W) uint16 with ``depth_scale`` = :data:`DEPTH_SCALE` (5000 units per metre,
as TUM), like every source. Clean depth (float32 metres, unquantised, unlimited range) is
kept in ``depth_gt`` and is the frames' depth when ``sensor_noise`` is off (then
``depth_scale`` is None: exact geometry for tests, not a sensor stream). Everything is
deterministic from ``seed``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import overload

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.frames import FrameInput
from arlight.pipeline import sh
from arlight.pipeline.color import LUMA as LUMINANCE_RGB

SH_BANDS = 4
FIRST_TIMESTAMP_S = 1000.0
FRAME_RATE_HZ = 30.0
DEPTH_SCALE = 5000.0  # depth quantisation, units per metre (TUM)
DEPTH_RANGE_M = (0.4, 4.0)
DEPTH_DROPOUT_FRACTION = 0.01
COLOR_NOISE_SIGMA = 1.5 / 255.0
MID_GREY = 0.18
SHADOW_OFFSET_M = 1e-4  # shadow-ray origins leave the surface along the normal by this much
UP = np.array([0.0, 1.0, 0.0])

# orbit of the camera around the scene
ORBIT_RADIUS_M = 2.0
ORBIT_HEIGHT_M = 1.0
ORBIT_TARGET = np.array([0.0, 0.2, 0.0])
ORBIT_SWEEP_RAD = math.radians(75.0)
ORBIT_START_FROM_SUN_RAD = math.radians(70.0)  # side light first, then towards back light
# the orbit the command-line tools render when not told otherwise; `--max-frames N` takes its
# first N frames (a longer orbit for a larger N), never a coarser orbit: at 8 frames the
# camera steps 11 degrees a frame, and tracking loses it from the second frame on
CLI_FRAMES = 12

# light
SUN_ELEVATION_RANGE_RAD = (math.radians(30.0), math.radians(50.0))
SUN_RGB = 5.0 * np.array([1.0, 0.95, 0.86])
SKY_HORIZON_RGB = np.array([0.50, 0.56, 0.66])
SKY_ZENITH_RGB = np.array([0.50, 0.66, 1.00])
SKY_NADIR_RGB = np.array([0.20, 0.19, 0.17])  # ground bounce below the horizon
SKY_SUN_SIDE_RGB = np.array([0.12, 0.10, 0.07])
LIGHT_CHANGE_AZIMUTH_RAD = math.radians(110.0)

GROUND_ALBEDO = np.array([0.50, 0.48, 0.45])
GROUND_TEXTURE_AMPLITUDE = 0.15
GROUND_CHECKER_M = 0.25
GROUND_TEXTURE_FADE_M = (4.0, 8.0)  # full texture nearer than the first, none beyond the second


# ---------------------------------------------------------------------------------------------
# primitives
#
# Ray casting works on structure-of-arrays: points and directions are (3, N) float32 (one
# column per ray; a single origin or direction is a (3, 1) column broadcast over all rays).


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Column-wise dot product of (3, N) arrays (either may be a (3, 1) column)."""
    if b.shape[1] == 1:
        return b[:, 0] @ a
    if a.shape[1] == 1:
        return a[:, 0] @ b
    return np.einsum("ij,ij->j", a, b)


def _columns(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The columns `index` of a (3, N) array; a broadcast (3, 1) column stays as it is."""
    return a if a.shape[1] == 1 else a[:, index]


def _sphere_hit(
    centre: np.ndarray, radius: float, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Entry t (N,) and hit mask of rays against a sphere; origins outside it, t > 0."""
    oc = origins - centre[:, None]
    b = _dot(oc, dirs)
    disc = b * b - (_dot(oc, oc) - np.float32(radius * radius))
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return t, (disc >= 0) & (t > 0)


def _may_hit(
    centre: np.ndarray, radius: float, origins: np.ndarray, dirs: np.ndarray
) -> np.ndarray:
    """Indices of the rays (3, N) that meet a bounding sphere ahead of (or around) their
    origins: a conservative cull before exact tests."""
    oc = origins - centre[:, None]
    b = _dot(oc, dirs)
    c = _dot(oc, oc) - np.float32(radius * radius)
    disc = b * b - c
    may = (disc >= 0) & ((b < 0) | (c < 0))
    return np.flatnonzero(np.broadcast_to(may, (max(origins.shape[1], dirs.shape[1]),)))


@dataclass(frozen=True)
class Sphere:
    """Sphere: centre (x, y, z) world metres, radius metres, linear RGB albedo."""

    centre: tuple[float, float, float]
    radius: float
    albedo: tuple[float, float, float]

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter t (N,) of the first hit, inf = miss; origins outside the object.

        origins, dirs: (3, N) float32 or (3, 1) columns broadcast; dirs unit length.
        """
        t, hit = _sphere_hit(np.asarray(self.centre, np.float32), self.radius, origins, dirs)
        return np.where(hit, t, np.float32(np.inf))

    def bound(self) -> tuple[np.ndarray, float]:
        """Bounding sphere (centre, radius): the sphere itself."""
        return np.asarray(self.centre, np.float32), float(self.radius)

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Outward unit normals (3, N) at surface points (3, N)."""
        return (points - np.asarray(self.centre, np.float32)[:, None]) / np.float32(self.radius)

    def occluder(self) -> tuple[np.ndarray, float]:
        """(centre, radius) of the sphere used for ambient occlusion."""
        return np.asarray(self.centre, np.float32), float(self.radius)


@dataclass(frozen=True)
class Box:
    """Box yawed about +Y: centre world metres, half extents (x, y, z) in its own frame, yaw
    radians (right-handed about +Y), linear RGB albedo. It stands on the ground when
    centre y == half_extents y."""

    centre: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    yaw: float
    albedo: tuple[float, float, float]

    @property
    def world_from_box(self) -> np.ndarray:
        """(3, 3) float32 rotation, box axes as columns."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], np.float32)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Slab test behind a bounding-sphere cull; same contract as :meth:`Sphere.intersect`."""
        centre, bound = self.bound()
        index = _may_hit(centre, bound, origins, dirs)
        t = np.full(max(origins.shape[1], dirs.shape[1]), np.inf, np.float32)
        if index.size:
            t[index] = self._slab(_columns(origins, index), _columns(dirs, index))
        return t

    def bound(self) -> tuple[np.ndarray, float]:
        """Bounding sphere (centre, radius)."""
        return np.asarray(self.centre, np.float32), float(np.linalg.norm(self.half_extents))

    def _slab(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rot_t = self.world_from_box.T
        o = rot_t @ (origins - np.asarray(self.centre, np.float32)[:, None])
        d = rot_t @ dirs
        d = np.where(np.abs(d) < 1e-12, np.float32(1e-12), d)
        inv = np.float32(1.0) / d
        half = np.asarray(self.half_extents, np.float32)[:, None]
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        t_near = np.maximum(np.maximum(lo[0], lo[1]), lo[2])
        t_far = np.minimum(np.minimum(hi[0], hi[1]), hi[2])
        return np.where((t_near <= t_far) & (t_near > 0), t_near, np.float32(np.inf))

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Outward unit normals (3, N) of the faces that surface points (3, N) lie on."""
        rot = self.world_from_box
        q = (
            rot.T
            @ (points - np.asarray(self.centre, np.float32)[:, None])
            / np.asarray(self.half_extents, np.float32)[:, None]
        )
        axis = np.abs(q).argmax(axis=0)
        cols = np.arange(q.shape[1])
        n_box = np.zeros_like(q)
        n_box[axis, cols] = np.sign(q[axis, cols])
        return rot @ n_box

    def occluder(self) -> tuple[np.ndarray, float]:
        """Sphere of the box's volume at its centre (for ambient occlusion)."""
        volume = 8.0 * float(np.prod(self.half_extents))
        return np.asarray(self.centre, np.float32), (3.0 * volume / (4.0 * math.pi)) ** (1 / 3)


Primitive = Sphere | Box

SCENE_OBJECTS: tuple[Primitive, ...] = (
    Sphere((0.30, 0.16, 0.15), 0.16, (0.78, 0.78, 0.76)),
    Box((-0.28, 0.11, -0.12), (0.16, 0.11, 0.10), math.radians(30.0), (0.70, 0.16, 0.06)),
    Sphere((-0.18, 0.08, 0.42), 0.08, (0.45, 0.45, 0.45)),
    Box((0.32, 0.18, -0.40), (0.08, 0.18, 0.08), math.radians(-15.0), (0.62, 0.62, 0.60)),
)


@functools.lru_cache(maxsize=8)
def _cluster_bound(objects: tuple[Primitive, ...]) -> tuple[np.ndarray, float]:
    """A sphere (centre, radius) enclosing every object's bounding sphere."""
    bounds = [obj.bound() for obj in objects]
    centre = np.mean([c for c, _ in bounds], axis=0).astype(np.float32)
    radius = max(float(np.linalg.norm(c - centre)) + r for c, r in bounds)
    return centre, radius


def _intersect_all(
    origins: np.ndarray, dirs: np.ndarray, objects: tuple[Primitive, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest object hit of rays (3, N): t (N,) (inf = none) and object index (N,) (-1)."""
    n = max(origins.shape[1], dirs.shape[1])
    t = np.full(n, np.inf, np.float32)
    ids = np.full(n, -1, np.int16)
    if not objects:
        return t, ids
    index = _may_hit(*_cluster_bound(objects), origins, dirs)
    o, d = _columns(origins, index), _columns(dirs, index)
    t_sub = np.full(index.size, np.inf, np.float32)
    ids_sub = np.full(index.size, -1, np.int16)
    for k, obj in enumerate(objects):
        t_obj = obj.intersect(o, d)
        closer = t_obj < t_sub
        t_sub = np.where(closer, t_obj, t_sub)
        ids_sub[closer] = k
    t[index], ids[index] = t_sub, ids_sub
    return t, ids


# ---------------------------------------------------------------------------------------------
# lighting


def _quadratic_sh(a: float, b: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Exact SH (16,) of f(w) = a + b.w + w^T q w on the unit sphere (q symmetric 3x3).

    Uses  int w_i w_j dw = 4 pi / 3 delta_ij  and, for Y_2m = w^T B_m w with B_m traceless,
    int (w^T q w)(w^T B_m w) dw = 8 pi / 15 tr(q B_m). Bands 3 and up are zero.
    """
    k_xy = 0.5 * math.sqrt(15.0 / math.pi)  # Y_2,-2 = k_xy x y, also yz, xz
    k_20 = 0.25 * math.sqrt(5.0 / math.pi)  # Y_2,0 = k_20 (2 z^2 - x^2 - y^2) on the sphere
    k_22 = 0.25 * math.sqrt(15.0 / math.pi)  # Y_2,2 = k_22 (x^2 - y^2)
    w2 = 8.0 * math.pi / 15.0
    c = np.zeros(sh.num_coefficients(SH_BANDS))
    c[0] = math.sqrt(4.0 * math.pi) * (a + np.trace(q) / 3.0)
    c[1:4] = sh.Y1_SCALE * 4.0 * math.pi / 3.0 * np.asarray(b)[[1, 2, 0]]
    c[4] = w2 * k_xy * q[0, 1]
    c[5] = w2 * k_xy * q[1, 2]
    c[6] = w2 * k_20 * (2.0 * q[2, 2] - q[0, 0] - q[1, 1])
    c[7] = w2 * k_xy * q[0, 2]
    c[8] = w2 * k_22 * (q[0, 0] - q[1, 1])
    return c


def sun_direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector towards the sun; azimuth right-handed about +Y from +Z (R_y(az) of +Z)."""
    ce = math.cos(elevation)
    return np.array([ce * math.sin(azimuth), math.sin(elevation), ce * math.cos(azimuth)])


@dataclass(frozen=True)
class Lighting:
    """Distant light: a delta sun plus a whole-sphere quadratic sky (module docstring).

    sun_direction: (3,) unit, towards the sun, world. sun_rgb: (3,) integrated radiance of
    the delta (linear RGB). sky_*_rgb: (3,) sky radiance at the horizon, zenith, nadir;
    sky_sun_side_rgb: (3,) gain of the horizontal lobe towards the sun's azimuth.
    """

    sun_direction: np.ndarray
    sun_rgb: np.ndarray = field(default_factory=lambda: SUN_RGB.copy())
    sky_horizon_rgb: np.ndarray = field(default_factory=lambda: SKY_HORIZON_RGB.copy())
    sky_zenith_rgb: np.ndarray = field(default_factory=lambda: SKY_ZENITH_RGB.copy())
    sky_nadir_rgb: np.ndarray = field(default_factory=lambda: SKY_NADIR_RGB.copy())
    sky_sun_side_rgb: np.ndarray = field(default_factory=lambda: SKY_SUN_SIDE_RGB.copy())

    def _sky_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per channel (3,): a, b_y, q, g and the horizontal sun direction h (3,)."""
        a = self.sky_horizon_rgb
        b_y = 0.5 * (self.sky_zenith_rgb - self.sky_nadir_rgb)
        q = 0.5 * (self.sky_zenith_rgb + self.sky_nadir_rgb) - a
        h = np.array([self.sun_direction[0], 0.0, self.sun_direction[2]])
        return a, b_y, q, h / np.linalg.norm(h)

    def sky_radiance(self, dirs: np.ndarray) -> np.ndarray:
        """Sky radiance (..., 3) linear RGB at unit world directions (..., 3); no sun."""
        a, b_y, q, h = self._sky_terms()
        y = dirs[..., 1:2]
        side = dirs @ h.astype(dirs.dtype)
        return (a + b_y * y + q * y * y + self.sky_sun_side_rgb * side[..., None]).astype(
            dirs.dtype
        )

    def sky_sh_rgb(self) -> np.ndarray:
        """Exact radiance SH (3, 16) of the sky, world frame."""
        a, b_y, q, h = self._sky_terms()
        qq = np.zeros((3, 3))
        rows = []
        for ch in range(3):
            qq[1, 1] = q[ch]
            rows.append(_quadratic_sh(a[ch], b_y[ch] * UP + self.sky_sun_side_rgb[ch] * h, qq))
        return np.array(rows)

    def sh_rgb(self) -> np.ndarray:
        """Radiance SH (3, 16) of the whole environment (sky + sun), world frame."""
        sun = np.outer(self.sun_rgb, sh.directional_light(self.sun_direction, 1.0, SH_BANDS))
        return self.sky_sh_rgb() + sun

    def sh_luminance(self) -> np.ndarray:
        """Radiance SH (16,) of the environment's luminance: the ground truth."""
        return LUMINANCE_RGB @ self.sh_rgb()

    def sky_irradiance(self, normals: np.ndarray) -> np.ndarray:
        """Irradiance (N, 3) from the whole-sphere sky on surfaces with unit normals (N, 3)."""
        e = sh.irradiance_from_radiance(self.sky_sh_rgb())[:, :9]  # the sky has bands 0..2
        return (sh.sh_basis(normals, 3) @ e.T).astype(np.float32)


def make_lighting(azimuth: float, elevation: float) -> Lighting:
    """The scene's sky and sun with the sun at (azimuth, elevation), radians."""
    return Lighting(sun_direction=sun_direction(azimuth, elevation))


def exposure_for(lighting: Lighting) -> float:
    """Exposure mapping sunlit ground of mean albedo to linear MID_GREY (luminance)."""
    sky = lighting.sky_irradiance(UP[None])[0]
    e_rgb = lighting.sun_rgb * max(0.0, float(lighting.sun_direction[1])) + sky
    radiance = float(LUMINANCE_RGB @ (GROUND_ALBEDO * e_rgb)) / math.pi
    return MID_GREY / radiance


# ---------------------------------------------------------------------------------------------
# rendering (structure-of-arrays, see "primitives")


def ground_albedo(points: np.ndarray, distance_m: np.ndarray) -> np.ndarray:
    """Ground albedo (3, N) at ground points (3, N) seen from `distance_m` (N,) away."""
    x, z = points[0], points[2]
    k = np.float32(math.pi / GROUND_CHECKER_M)
    checker = np.clip(np.float32(3.0) * np.sin(k * x) * np.sin(k * z), -1.0, 1.0)
    noise = (
        np.sin(3.1 * x + 1.3 * z + 0.4)
        + np.sin(-1.7 * x + 4.3 * z + 2.1)
        + np.sin(5.9 * x - 0.7 * z + 4.0)
    ) / 3.0
    near, far = GROUND_TEXTURE_FADE_M
    fade = np.clip((far - distance_m) / (far - near), 0.0, 1.0)
    tex = np.float32(GROUND_TEXTURE_AMPLITUDE) * fade * (0.5 * checker + 0.5 * noise)
    return GROUND_ALBEDO.astype(np.float32)[:, None] * (1.0 + tex)


def sun_visibility(
    points: np.ndarray,
    normals: np.ndarray,
    direction: np.ndarray,
    objects: tuple[Primitive, ...] = SCENE_OBJECTS,
) -> np.ndarray:
    """1 where the sun (unit `direction`, (3,)) is unoccluded from surface points, else 0.

    points, normals: (3, N) float32. The ground never occludes (the sun is above the
    horizon); shadow rays start SHADOW_OFFSET_M off the surface along the normals.
    """
    origins = points + np.float32(SHADOW_OFFSET_M) * normals
    t, _ = _intersect_all(origins, np.asarray(direction, np.float32)[:, None], objects)
    return np.isinf(t).astype(np.float32)


def ambient_occlusion(
    points: np.ndarray, normals: np.ndarray, objects: tuple[Primitive, ...] = SCENE_OBJECTS
) -> np.ndarray:
    """Fraction (N,) of cosine-weighted sky left open by the objects, each seen as a sphere.

    points, normals: (3, N) float32. A sphere of radius r at distance d, fully above the
    tangent plane, hides (r / d)^2 cos(angle to its centre) of the cosine-weighted hemisphere.
    """
    hidden = np.zeros(points.shape[1], np.float32)
    for obj in objects:
        centre, radius = obj.occluder()
        v = centre[:, None] - points
        dist2 = np.maximum(_dot(v, v), np.float32(radius**2))
        cos = np.maximum(_dot(v, normals), 0.0) / np.sqrt(dist2)
        hidden += np.float32(radius**2) / dist2 * cos
    return 1.0 - np.minimum(hidden, np.float32(0.8))


def _cast(
    origin: np.ndarray, dirs: np.ndarray, t_ground: np.ndarray, objects: tuple[Primitive, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays (3, N) from one origin (3, 1) given their ground hits t_ground (N,)
    float64: t (N,) float64 (inf = nothing) and id (N,) (-1 sky, 0 ground, 1 + k object k)."""
    ids = np.where(np.isfinite(t_ground), 0, -1).astype(np.int16)
    t_obj, k_obj = _intersect_all(origin, dirs, objects)
    closer = t_obj < t_ground
    return np.where(closer, t_obj, t_ground), np.where(closer, k_obj + 1, ids).astype(np.int16)


def _ground_hits(world_from_cam: np.ndarray, rays_cam: np.ndarray) -> np.ndarray:
    """Ray parameter (N,) float64 where camera rays (3, N) meet y = 0, inf above the horizon.

    In float64: near the horizon the float32 direction would cost centimetres of depth.
    """
    dirs_y = world_from_cam[1, :3] @ rays_cam
    with np.errstate(divide="ignore"):
        return np.where(dirs_y < 0, -world_from_cam[1, 3] / dirs_y, np.inf)


def _surface(
    points: np.ndarray, ids: np.ndarray, t: np.ndarray, objects: tuple[Primitive, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (3, N) and albedo (3, N) at hit points (3, N); ids < 1 get the ground's."""
    normals = np.zeros_like(points)
    normals[1] = 1.0
    albedo = ground_albedo(points, t)
    for k, obj in enumerate(objects):
        index = np.flatnonzero(ids == k + 1)
        normals[:, index] = obj.normals(points[:, index])
        albedo[:, index] = np.asarray(obj.albedo, np.float32)[:, None]
    return normals, albedo


def _sky_irradiance(lighting: Lighting, normals: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Sky irradiance (3, N); ground points (ids < 1, all facing +Y) share one value."""
    e = np.empty_like(normals)
    e[:] = lighting.sky_irradiance(UP[None])[0][:, None]
    index = np.flatnonzero(ids > 0)
    e[:, index] = lighting.sky_irradiance(normals[:, index].T).T
    return e


def _shade(
    points: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
    ids: np.ndarray,
    lighting: Lighting,
    objects: tuple[Primitive, ...],
) -> np.ndarray:
    """Lambertian outgoing radiance (3, N) (module docstring)."""
    s = np.asarray(lighting.sun_direction, np.float32)
    cos_sun = np.maximum(_dot(normals, s[:, None]), 0.0)
    cos_sun *= sun_visibility(points, normals, s, objects)
    sky = _sky_irradiance(lighting, normals, ids)
    sky *= ambient_occlusion(points, normals, objects)
    sun = lighting.sun_rgb.astype(np.float32)[:, None] * cos_sun
    return albedo * np.float32(1.0 / math.pi) * (sun + sky)


def render_frame(
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    lighting: Lighting,
    objects: tuple[Primitive, ...] = SCENE_OBJECTS,
    rays_cam: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance (H, W, 3) float32 and clean depth (H, W) float32 (camera z, metres,
    0 = sky) of the scene seen from the pose `world_from_cam` (4, 4), OpenCV camera axes.

    rays_cam: optional precomputed unit rays (3, H*W) float32, camera frame, row-major
    pixels (``camera.ray_directions().reshape(-1, 3).T``).
    """
    if rays_cam is None:
        rays_cam = np.ascontiguousarray(camera.ray_directions().reshape(-1, 3).T)
    pose = np.asarray(world_from_cam, np.float64)
    dirs = pose[:3, :3].astype(np.float32) @ rays_cam
    origin = pose[:3, 3:4].astype(np.float32)
    t, ids = _cast(origin, dirs, _ground_hits(pose, rays_cam), objects)

    # every pixel is shaded as a surface (sky pixels at the camera), then the sky overwrites
    t_hit64 = np.where(ids >= 0, t, 0.0)
    t_hit = t_hit64.astype(np.float32)
    points = origin + t_hit * dirs
    normals, albedo = _surface(points, ids, t_hit, objects)
    radiance = _shade(points, normals, albedo, ids, lighting, objects)
    sky = np.flatnonzero(ids < 0)
    radiance[:, sky] = lighting.sky_radiance(dirs[:, sky].T).T

    shape = (camera.height, camera.width)
    depth = (t_hit64 * rays_cam[2]).astype(np.float32).reshape(shape)
    return np.ascontiguousarray(radiance.T).reshape(shape + (3,)), depth


# ---------------------------------------------------------------------------------------------
# sensor


def _srgb_lut(size: int = 65536) -> np.ndarray:
    """sRGB encoding of linear [0, 1] sampled at `size` steps, scaled to [0, 255]."""
    x = np.linspace(0.0, 1.0, size)
    return 255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


_SRGB_LUT_255 = _srgb_lut().astype(np.float32)


def encode_color(
    radiance: np.ndarray, exposure: float, rng: np.random.Generator | None = None
) -> np.ndarray:
    """uint8 sRGB (H, W, 3) of clip(exposure * radiance, 0, 1) (linear radiance (H, W, 3));
    Gaussian noise of sigma COLOR_NOISE_SIGMA added before rounding when `rng` is given."""
    top = len(_SRGB_LUT_255) - 1
    scaled = radiance * np.float32(exposure * top)
    np.clip(scaled, 0.0, top, out=scaled)
    encoded = _SRGB_LUT_255[(scaled + np.float32(0.5)).astype(np.uint16)]
    if rng is not None:
        noise = rng.standard_normal(encoded.shape, np.float32)
        noise *= np.float32(255.0 * COLOR_NOISE_SIGMA)
        encoded += noise
    np.clip(encoded, 0.0, 255.0, out=encoded)
    return np.rint(encoded, out=encoded).astype(np.uint8)


def _depth_edges(depth: np.ndarray) -> np.ndarray:
    """Mask of pixels beside a depth jump > max(3 cm, 3 % z) or a depth/sky boundary."""
    edge = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a = depth.take(np.arange(depth.shape[axis] - 1), axis=axis)
        b = depth.take(np.arange(1, depth.shape[axis]), axis=axis)
        jump = np.abs(a - b) > np.maximum(0.03, 0.03 * np.minimum(a, b))
        jump |= (a > 0) != (b > 0)
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis], pad_hi[axis] = (1, 0), (0, 1)
        edge |= np.pad(jump, pad_lo) | np.pad(jump, pad_hi)
    return edge


def kinect_depth(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Kinect-v1-like sensor depth (H, W) uint16 at DEPTH_SCALE units per metre (0 = missing)
    from clean depth (H, W) float32 metres (0 = missing)."""
    z = depth.astype(np.float32)
    sigma = 0.0012 + 0.0019 * (z - np.float32(DEPTH_RANGE_M[0])) ** 2
    noisy = z + rng.standard_normal(z.shape, np.float32) * sigma
    drop = rng.random(z.shape, np.float32) < DEPTH_DROPOUT_FRACTION
    valid = (z > 0) & (noisy >= DEPTH_RANGE_M[0]) & (noisy <= DEPTH_RANGE_M[1])
    valid &= ~drop & ~_depth_edges(z)
    units = np.rint(noisy * np.float32(DEPTH_SCALE))  # <= 4.0 m * 5000: fits in uint16
    return np.where(valid, units, 0.0).astype(np.uint16)


# ---------------------------------------------------------------------------------------------
# sequence


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_from_cam (4, 4), OpenCV axes: z towards `target`, x right, y down (world -Y-ish)."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, UP)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def orbit_poses(num_frames: int, start_azimuth: float) -> list[np.ndarray]:
    """Camera-to-world poses on the orbit, sweeping ORBIT_SWEEP_RAD from `start_azimuth`."""
    poses = []
    for i in range(num_frames):
        phi = start_azimuth + ORBIT_SWEEP_RAD * (i / max(1, num_frames - 1))
        eye = np.array(
            [ORBIT_RADIUS_M * math.sin(phi), ORBIT_HEIGHT_M, ORBIT_RADIUS_M * math.cos(phi)]
        )
        poses.append(look_at(eye, ORBIT_TARGET))
    return poses


# a camera held in the hand: the first pose of the orbit, each frame off it by a tremor of
# this size (1-sigma per axis, metres and radians; a held tablet: a millimetre, 0.05 deg)
TREMOR_M = 0.001
TREMOR_RAD = math.radians(0.05)


def held_poses(
    num_frames: int,
    start_azimuth: float,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """Camera-to-world poses of a camera held still at the orbit's start (hand tremor)."""
    from scipy.spatial.transform import Rotation

    start = orbit_poses(1, start_azimuth)[0]
    poses = []
    for _ in range(num_frames):
        pose = start.copy()
        pose[:3, :3] = (
            Rotation.from_rotvec(rng.normal(0.0, TREMOR_RAD, 3)).as_matrix() @ start[:3, :3]
        )
        pose[:3, 3] += rng.normal(0.0, TREMOR_M, 3)
        poses.append(pose)
    return poses


@dataclass
class SyntheticSequence:
    """A rendered sequence and its ground truth (module docstring for the definitions).

    frames: FrameInput per frame, pose = world_from_cam (4, 4), timestamp 1000 + i / 30 s;
        depth uint16 at depth_scale DEPTH_SCALE (sensor_noise) or clean float32 metres.
    sh_world: (16,) per frame, luminance radiance SH of the environment, world frame, arlight
        basis, radiance units before exposure. sh_rgb_world: (3, 16) per frame, per channel.
    dominant_direction_world / _camera: (3,) per frame, sh.dominant_direction(sh_world) and
        R_wc^T of it. sun_direction_world: (3,) per frame, towards the sun.
    exposure: linear scale applied before clipping and sRGB encoding.
    depth_gt: (H, W) float32 per frame, clean camera z in metres, 0 = sky.
    """

    name: str
    camera: PinholeCamera
    frames: list[FrameInput]
    sh_world: list[np.ndarray]
    dominant_direction_world: list[np.ndarray]
    dominant_direction_camera: list[np.ndarray]
    exposure: float
    sun_direction_world: list[np.ndarray]
    sh_rgb_world: list[np.ndarray] = field(default_factory=list)
    depth_gt: list[np.ndarray] = field(default_factory=list)
    light_change_frame: int | None = None

    def __len__(self) -> int:
        return len(self.frames)


MAX_PIXELS = 3840 * 2160  # 4K: the scene renders in memory (~1 KiB per pixel)


def parse_size(text: str) -> tuple[int, int]:
    """(width, height) of "WIDTHxHEIGHT" for the scene: 8x8 up to MAX_PIXELS; ValueError."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"expected WIDTHxHEIGHT, e.g. 320x240, got {text!r}") from None
    if w < 8 or h < 8:
        raise ValueError(f"size must be at least 8x8, got {w}x{h}")
    if w * h > MAX_PIXELS:
        raise ValueError(
            f"size {w}x{h} is larger than the built-in scene renders (at most 3840x2160 pixels)"
        )
    return w, h


def _check_arguments(
    num_frames: int, width: int, height: int, light_change_frame: int | None
) -> None:
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be >= 1x1 pixels, got {width}x{height}")
    if light_change_frame is not None and not 0 <= light_change_frame < num_frames:
        raise ValueError(
            f"light_change_frame must be in [0, {num_frames - 1}] or None, got {light_change_frame}"
        )


@dataclass(frozen=True)
class _Setup:
    """What every frame of one sequence shares: camera, the two lights, exposure, poses."""

    camera: PinholeCamera
    lights: tuple[Lighting, Lighting]
    exposure: float
    poses: list[np.ndarray]
    name: str


def _setup(num_frames: int, width: int, height: int, seed: int, held: bool) -> _Setup:
    scene_rng = np.random.default_rng([seed, 0])
    azimuth = float(scene_rng.uniform(0.0, 2.0 * math.pi))
    elevation = float(scene_rng.uniform(*SUN_ELEVATION_RANGE_RAD))
    lights = (
        make_lighting(azimuth, elevation),
        make_lighting(azimuth + LIGHT_CHANGE_AZIMUTH_RAD, elevation),
    )
    start = azimuth + ORBIT_START_FROM_SUN_RAD
    poses = (
        held_poses(num_frames, start, np.random.default_rng([seed, 2]))
        if held
        else orbit_poses(num_frames, start)
    )
    return _Setup(
        camera=PinholeCamera.kinect_v1(width, height),
        lights=lights,
        exposure=exposure_for(lights[0]),  # same elevation after a change: same ground
        poses=poses,
        name=f"arlight_synthetic{'_held' if held else ''}_seed{seed}",
    )


def _render_frames(
    setup: _Setup, seed: int, sensor_noise: bool, light_change_frame: int | None
) -> Iterator[tuple[FrameInput, Lighting, np.ndarray]]:
    """(frame, its light, its clean depth in metres) per pose, rendered one at a time in
    order (the sensor noise draws from one generator, so the order is part of the output)."""
    noise_rng = np.random.default_rng([seed, 1])
    camera = setup.camera
    rays_cam = np.ascontiguousarray(camera.ray_directions().reshape(-1, 3).T)
    for i, pose in enumerate(setup.poses):
        changed = light_change_frame is not None and i >= light_change_frame
        light = setup.lights[int(changed)]
        radiance, depth = render_frame(camera, pose, light, rays_cam=rays_cam)
        rng = noise_rng if sensor_noise else None
        color = encode_color(radiance, setup.exposure, rng)
        if sensor_noise:
            sensor_depth, depth_scale = kinect_depth(depth, noise_rng), DEPTH_SCALE
        else:
            sensor_depth, depth_scale = depth, None
        frame = FrameInput(
            color=color,
            depth=sensor_depth,
            depth_scale=depth_scale,
            pose=pose,
            timestamp=FIRST_TIMESTAMP_S + i / FRAME_RATE_HZ,
        )
        yield frame, light, depth


def make_sequence(
    num_frames: int = 12,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    sensor_noise: bool = True,
    light_change_frame: int | None = None,
    held: bool = False,
) -> SyntheticSequence:
    """Render the procedural scene along an orbit (module docstring), deterministically;
    held: a camera held still at the orbit's start instead (`held_poses`).

    seed picks the sun (azimuth in [0, 2 pi), elevation 30-50 degrees; the orbit starts
    70 degrees round from the sun's azimuth) and the sensor noise. From
    `light_change_frame` on, the sun is 110 degrees further round in azimuth.
    Every frame is rendered before it returns: a stream uses :class:`LazyFrames`.
    """
    _check_arguments(num_frames, width, height, light_change_frame)
    setup = _setup(num_frames, width, height, seed, held)
    seq = SyntheticSequence(
        name=setup.name,
        camera=setup.camera,
        frames=[],
        sh_world=[],
        dominant_direction_world=[],
        dominant_direction_camera=[],
        exposure=setup.exposure,
        sun_direction_world=[],
        light_change_frame=light_change_frame,
    )
    rendered = _render_frames(setup, seed, sensor_noise, light_change_frame)
    for pose, (frame, light, depth) in zip(setup.poses, rendered, strict=True):
        seq.frames.append(frame)
        _append_ground_truth(seq, light, pose)
        seq.depth_gt.append(depth)
    return seq


LAZY_CACHE_BYTES = 256 * 2**20  # frames kept once rendered (a --loop re-renders past this)


class LazyFrames(Sequence[FrameInput]):
    """The frames of ``make_sequence(num_frames, width, height, seed)`` (sensor noise on),
    rendered when first asked for, in order, so a stream of 100000 frames sends its first
    at once: ``len`` is known up front, ``frames[i]`` renders up to i. The first frames, up
    to LAZY_CACHE_BYTES, are kept; asking again for a frame past them renders the sequence
    anew from the start (same bytes: deterministic). use_poses False: pose None. first:
    only the orbit's first frames (at most num_frames)."""

    def __init__(
        self,
        num_frames: int,
        width: int,
        height: int,
        seed: int = 0,
        use_poses: bool = True,
        first: int | None = None,
    ):
        _check_arguments(num_frames, width, height, None)
        self._setup = _setup(num_frames, width, height, seed, held=False)
        self._seed, self._use_poses = seed, use_poses
        self._n = num_frames if first is None else max(0, min(first, num_frames))
        self._cache: list[FrameInput] = []
        self._cache_max = max(1, LAZY_CACHE_BYTES // (width * height * 5))  # RGB + uint16
        self._it: Iterator[tuple[FrameInput, Lighting, np.ndarray]] | None = None
        self._next = 0  # the index the iterator yields next
        self._last: tuple[int, FrameInput] | None = None

    @property
    def camera(self) -> PinholeCamera:
        return self._setup.camera

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, i: int) -> FrameInput: ...
    @overload
    def __getitem__(self, i: slice) -> list[FrameInput]: ...
    def __getitem__(self, i: int | slice) -> FrameInput | list[FrameInput]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self._n))]
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(f"frame {i} of {self._n}")
        if i < len(self._cache):
            return self._cache[i]
        if self._last is not None and self._last[0] == i:
            return self._last[1]
        if self._it is None or self._next > i:
            self._it = _render_frames(self._setup, self._seed, True, None)
            self._next = 0
        while True:
            frame = next(self._it)[0]
            if not self._use_poses:
                frame = dataclasses.replace(frame, pose=None)
            index, self._next = self._next, self._next + 1
            if index == len(self._cache) and index < self._cache_max:
                self._cache.append(frame)
            if index == i:
                self._last = (i, frame)
                return frame


def _append_ground_truth(seq: SyntheticSequence, light: Lighting, pose: np.ndarray) -> None:
    sh_rgb = light.sh_rgb()
    sh_lum = LUMINANCE_RGB @ sh_rgb
    dominant = sh.dominant_direction(sh_lum)
    seq.sh_rgb_world.append(sh_rgb)
    seq.sh_world.append(sh_lum)
    seq.dominant_direction_world.append(dominant)
    seq.dominant_direction_camera.append(pose[:3, :3].T @ dominant)
    seq.sun_direction_world.append(np.asarray(light.sun_direction, float).copy())
