"""Hard shadows of a compact light source, both ways, for the composite.

A compact source (compact_light.CompactSource: direction w, integrated luminance k,
angular radius r) lights a surface point x with normal n by k V(x) max(0, n . w), where
V(x) in [0, 1] is the fraction of the source's disc seen from x: `samples` rays towards
directions spread over the disc (a fixed, seeded pattern: the penumbra's width follows
r and the occluder's distance), each blocked or not by a mesh at any distance.

For the composite (rendering.DifferentialRenderer): a real pixel lit by the source loses
k max(0, n . w) (1 - V_virtual) of its irradiance where a virtual object blocks it, and the
SH part (SSDO) changes the rest of its light, E_rest (the ambient SH's irradiance), by
rho = R'_d / R_d; so its observed colour is scaled by
(rho E_rest + k cos V_virtual V_real) / (E_rest + k cos V_real) in one step (decision 0053:
rho scales the ambient's share of the pixel's light, not the source's). A virtual pixel
gains k cos V_virtual V_real (its own shadow and the real scene's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numba
import numpy as np
import open3d as o3d
import open3d.core as o3c

from arlight.pipeline import sh
from arlight.pipeline.color import srgb_to_linear
from arlight.pipeline.srgb_encoding import (
    TABLE_BASE,
    TABLE_NEXT,
    counted_code,
    linear_to_srgb_u8,
)

RAY_OFFSET_M = 0.01  # rays start this far along the normal (metres)
# the SH part's change of a real pixel below both of these (its ratio's distance from 1, its
# added linear RGB) is left as the SH part drew it (far under an 8-bit step): no rays there
RATIO_CHANGE = 1e-3
INDIRECT_CHANGE = 1e-4
RAY_TNEAR_M = 0.002


def perpendicular_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) that with the unit `direction` make a right-handed basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(direction[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(direction, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(direction, e1)


def disc_directions(direction: np.ndarray, angular_radius_deg: float, samples: int) -> np.ndarray:
    """(S, 3) unit directions spread evenly over a disc of the given angular radius around
    `direction` (S = 1: the centre only). Deterministic (a Fibonacci spiral)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    if samples <= 1 or angular_radius_deg <= 0.0:
        return d[None]
    e1, e2 = perpendicular_basis(d)
    i = np.arange(samples) + 0.5
    radius = math.tan(math.radians(angular_radius_deg)) * np.sqrt(i / samples)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    out = d + radius[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


class MeshOccluder:
    """Triangle meshes (world frame) that block rays, in an Open3D RaycastingScene."""

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]]):
        """meshes: (vertices (N, 3) metres, triangles (M, 3) indices) per mesh, world frame."""
        self._scene = o3d.t.geometry.RaycastingScene()
        self.empty = True
        used = []
        for vertices, triangles in meshes:
            if len(triangles):
                self._scene.add_triangles(
                    o3c.Tensor(np.ascontiguousarray(vertices, np.float32)),
                    o3c.Tensor(np.ascontiguousarray(triangles).astype(np.uint32)),
                )
                self.empty = False
                used.append(np.asarray(vertices, np.float64)[np.unique(triangles)])
        # a sphere holding every triangle (world frame): rays that miss it hit nothing
        points = np.concatenate(used) if used else np.zeros((1, 3))
        self.centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
        self.radius = float(np.linalg.norm(points - self.centre, axis=1).max())

    def may_block(
        self,
        points: np.ndarray,
        direction: np.ndarray,
        angular_radius_deg: float,
        centre: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N,) bool: False where no ray from `points` (N, 3) within `angular_radius_deg` of
        unit `direction` can meet the meshes (it misses their bounding sphere, grown by the
        rays' offset); True where one may. `centre`: the sphere's centre in the frame of
        `points` and `direction` (default: world, the meshes' frame)."""
        c = self.centre if centre is None else np.asarray(centre, np.float64)
        a = math.radians(angular_radius_deg)
        out = np.empty(len(points), bool)
        _may_block_kernel(
            np.ascontiguousarray(points, np.float32),
            c.astype(np.float32),
            np.asarray(direction, np.float32),
            np.float32(self.radius + 2.0 * RAY_OFFSET_M),
            np.float32(math.cos(a)),
            np.float32(math.sin(a)),
            out,
        )
        return out

    def visibility(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        direction: np.ndarray,
        angular_radius_deg: float,
        samples: int = 8,
    ) -> np.ndarray:
        """(N,) fraction of the source's disc seen from each point (world frame; points
        (N, 3), normals (N, 3) unit; facing away from the source: 0 not tested, returns 1
        there so that a caller's cosine decides)."""
        n = len(points)
        if self.empty or n == 0:
            return np.ones(n)
        dirs = disc_directions(direction, angular_radius_deg, samples).astype(np.float32)
        origins = (points + RAY_OFFSET_M * normals).astype(np.float32)
        # every direction's rays in one call: (directions, points) rays
        rays = np.empty((len(dirs), n, 6), np.float32)
        rays[:, :, :3] = origins
        rays[:, :, 3:] = dirs[:, None, :]
        blocked = self._scene.test_occlusions(
            o3c.Tensor.from_numpy(rays.reshape(-1, 6)), tnear=RAY_TNEAR_M, tfar=np.inf
        ).numpy()
        # (counts of unblocked rays: exact in any order of summation)
        return (~blocked).reshape(len(dirs), n).sum(axis=0, dtype=np.float64) / len(dirs)


@numba.njit(parallel=True, cache=True)
def _real_pixels(virtual, points, normals, out):
    """out = ~virtual & (z > 0) & a normal (any component not zero, NaN counting as one),
    (H, W), in one pass."""
    for y in numba.prange(virtual.shape[0]):
        for x in range(virtual.shape[1]):
            out[y, x] = (
                not virtual[y, x]
                and points[y, x, 2] > 0
                and (normals[y, x, 0] != 0 or normals[y, x, 1] != 0 or normals[y, x, 2] != 0)
            )


@numba.njit(parallel=True, cache=True)
def _may_block_kernel(points, centre, direction, radius, cos_a, sin_a, out):
    """`MeshOccluder.may_block` per point, in float32: the cone of the disc's rays (half-angle
    a) meets the sphere (centre, radius) where the angle to its centre is at most a + b,
    b = asin(radius / dist) the sphere's angular radius: cos(angle) >= cos(a + b) =
    cos a cos b - sin a sin b, all times dist; a millimetre's margin over the rounding."""
    margin = np.float32(1e-3)
    for i in numba.prange(points.shape[0]):
        vx = centre[0] - points[i, 0]
        vy = centre[1] - points[i, 1]
        vz = centre[2] - points[i, 2]
        dist_sq = vx * vx + vy * vy + vz * vz
        dist = np.sqrt(dist_sq)
        along = vx * direction[0] + vy * direction[1] + vz * direction[2]  # dist cos(angle)
        cos_b_dist = np.sqrt(max(dist_sq - radius * radius, np.float32(0.0)))
        reach = cos_a * cos_b_dist - sin_a * radius
        out[i] = dist <= radius + margin or along >= reach - margin


def real_surface_factor(
    ambient_irradiance: np.ndarray,
    source_before: np.ndarray,
    source_after: np.ndarray,
    ambient_ratio: np.ndarray | float = 1.0,
) -> np.ndarray:
    """(N,) the factor that takes a real surface's observed colour to its colour with the
    virtual objects: (rho E + S_after) / (E + S_before), with E the ambient irradiance, rho
    the objects' change of it (SSDO's R'_d / R_d), S_before = k max(0, n . w) V_r the
    source's irradiance past the real geometry and S_after = S_before V_v past the virtual
    objects too. rho where the surface gets no light at all."""
    e = np.maximum(ambient_irradiance, 0.0)
    rho = np.broadcast_to(np.asarray(ambient_ratio, np.float64), e.shape)
    before = e + np.maximum(source_before, 0.0)
    after = rho * e + np.maximum(source_after, 0.0)
    return np.where(before > 1e-12, after / np.maximum(before, 1e-12), rho)


@dataclass(frozen=True)
class SourceLight:
    """A compact source as the renderer draws it: direction (3,) unit, world frame, towards
    it; irradiance: on a surface facing it, linear image units (the renderer's light_sh
    scale); rgb: (3,) its colour relative to the renderer's light_rgb (ones: the same);
    angular_radius_deg."""

    direction: np.ndarray
    irradiance: float
    rgb: np.ndarray
    angular_radius_deg: float


class RealOccluder(Protocol):
    """The reconstruction as an occluder (object_space_transfer.OcclusionScene)."""

    in_world: bool

    def blocked(self, rays: np.ndarray, tnear: float, tfar: float) -> np.ndarray: ...


def real_visibility(
    occluder: RealOccluder | None,
    points_world: np.ndarray,
    normals_world: np.ndarray,
    direction: np.ndarray,
    world_from_cam: np.ndarray,
) -> np.ndarray:
    """(N,) 1 where the ray towards `direction` leaves the reconstruction, 0 where it is
    blocked (one ray at the source's centre: the real penumbra is in the image already);
    all 1 without an occluder."""
    n = len(points_world)
    if occluder is None or n == 0:
        return np.ones(n)
    origins = points_world + 2.0 * RAY_OFFSET_M * normals_world
    d = np.asarray(direction, np.float64)
    if not occluder.in_world:  # a depth image's mesh: camera frame
        rot, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
        origins, d = (origins - t) @ rot, d @ rot
    rays = np.empty((n, 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = d
    return (~occluder.blocked(rays, 2.0 * RAY_OFFSET_M, 100.0)).astype(np.float64)


@dataclass(frozen=True)
class AmbientChange:
    """What the SH part of the differential rendering did to the real pixels of the
    rectangle it worked in, rows v0.. and columns u0.. (`origin` (v0, u0)): ratio (h, w), the
    factor R'_d / R_d on the observed colour (1 where unchanged); delta (h, w, 3), the linear
    RGB it added (the indirect change; 0 where unchanged); both read at real pixels only
    (a virtual pixel's are not defined); touched (H, W), the whole frame: real pixels where
    either changed enough to matter (`touched_by`)."""

    origin: tuple[int, int]
    ratio: np.ndarray
    delta: np.ndarray
    touched: np.ndarray


def touched_by(ratio: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """(...) bool: where the SH part's ratio (...) or added RGB (..., 3) changed a real
    pixel by more than RATIO_CHANGE / INDIRECT_CHANGE."""
    out = np.abs(ratio - 1.0) > RATIO_CHANGE
    for channel in range(delta.shape[-1]):  # (a max over the short last axis is slow)
        out |= np.abs(delta[..., channel]) > INDIRECT_CHANGE
    return out


class CompactSourceShading:
    """A virtual scene's shadows from compact sources, both ways, on a composite.

    Virtual pixels gain albedo / pi * S V_virtual V_real (S = irradiance max(0, n . w)).
    A real pixel's observed colour is lit by the ambient part E and the source S V_real;
    the virtual objects change the first by the SH renderer's ratio rho (SSDO, `AmbientChange`)
    and the second by V_virtual, so its colour is scaled by
    (rho E + S V_real V_virtual) / (E + S V_real) (`real_surface_factor`): the SSDO ratio
    weighs only the ambient share of the pixel's light, not the source's.
    Rays: from every real pixel facing the source whose cone of rays may meet the objects
    (`MeshOccluder.may_block`), at the disc's centre, then `samples` over the disc for those
    near a blocked one (the penumbra); V_real for the pixels that change; from every
    virtual pixel facing the source, `samples` over the disc and V_real."""

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]], samples: int = 8):
        self.virtual = MeshOccluder(meshes)
        self.samples = samples

    def apply(
        self,
        composite: np.ndarray,
        virtual: np.ndarray,
        virtual_normals_cam: np.ndarray,
        virtual_albedo: np.ndarray,
        virtual_points_cam: np.ndarray,
        real_points_cam: np.ndarray,
        real_normals_cam: np.ndarray,
        world_from_cam: np.ndarray,
        ambient_sh: np.ndarray,
        light_rgb: np.ndarray,
        sources: list[SourceLight],
        real_occluder: RealOccluder | None,
        color_linear: np.ndarray,
        ambient_change: AmbientChange | None,
        virtual_linear: np.ndarray | None = None,
    ) -> np.ndarray:
        """Shade `composite` ((H, W, 3) uint8 sRGB, in place); returns the (H, W) bool mask
        of the pixels changed. Points and normals: camera frame (zeros: none);
        virtual_points_cam and the virtual normals and albedo are read at `virtual` only.
        color_linear: (H, W, 3) the observed frame, linear; ambient_change: what the SH part
        did to the real pixels (None: nothing); virtual_linear: (K, 3) the linear RGB it drew
        the virtual pixels with, in np.nonzero(virtual)'s order (None: read back from
        `composite`, through its 8 bits). A real pixel the source's shadow or the SH
        part changed is made anew from its observed colour, the SSDO ratio weighing only
        the ambient's share of its light (class docstring)."""
        changed = np.zeros(virtual.shape, bool)
        rot, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
        real = np.empty(virtual.shape, bool)
        _real_pixels(virtual, real_points_cam, real_normals_cam, real)
        # virtual pixels: each source's light past their own and the real scene's shadow,
        # added to the SH part's linear colour, encoded once
        vv, vu = np.nonzero(virtual)
        if len(vv) and sources:
            linear = (
                srgb_to_linear(composite[vv, vu]).astype(np.float64)
                if virtual_linear is None
                else np.array(virtual_linear, np.float64)
            )
            p = virtual_points_cam[vv, vu].astype(np.float64) @ rot.T + t
            n = virtual_normals_cam[vv, vu].astype(np.float64) @ rot.T
            albedo = virtual_albedo[vv, vu].astype(np.float64)
            for source in sources:
                d = np.asarray(source.direction, np.float64)
                colour = np.asarray(source.rgb, np.float64) * np.asarray(light_rgb, np.float64)
                cos = np.maximum(n @ d, 0.0)
                lit = cos > 0.0  # rays only from pixels facing the source (else no light)
                seen = np.ones(len(vv))
                seen[lit] = self.virtual.visibility(
                    p[lit], n[lit], d, source.angular_radius_deg, self.samples
                ) * real_visibility(real_occluder, p[lit], n[lit], d, world_from_cam)
                add = (source.irradiance * cos * seen)[:, None] * colour
                linear += albedo / math.pi * add
            composite[vv, vu] = linear_to_srgb_u8(linear)
            changed[vv, vu] = True
        if self.virtual.empty or not sources:
            return changed
        # real pixels: the source's light before and after the objects, summed over sources
        touched_img = (
            real & ambient_change.touched
            if ambient_change is not None
            else np.zeros(virtual.shape, bool)
        )
        # only pixels the SH part touched or whose rays may meet the objects can change
        centre_cam = (self.virtual.centre - t) @ rot
        may_block = [  # per source (over every pixel: cheaper than gathering the real ones)
            self.virtual.may_block(
                real_points_cam.reshape(-1, 3),
                np.asarray(source.direction, np.float64) @ rot,
                source.angular_radius_deg,
                centre_cam,
            ).reshape(virtual.shape)
            for source in sources
        ]
        real &= np.logical_or.reduce([touched_img, *may_block])
        rv, ru = np.nonzero(real)  # (boolean masks below gather in this same order)
        rot32 = np.ascontiguousarray(rot.T, np.float32)
        p = real_points_cam[real] @ rot32 + t.astype(np.float32)  # float32: ray origins
        n = real_normals_cam[real] @ rot32
        touched = touched_img[real]
        before, after = np.zeros(len(rv)), np.zeros(len(rv))
        for source, may in zip(sources, may_block, strict=True):
            d = np.asarray(source.direction, np.float64)
            cos = n @ d.astype(np.float32)
            idx = np.flatnonzero(cos > 0.0)
            # rays only where they may meet the objects (elsewhere none is blocked)
            tested = may[rv[idx], ru[idx]]
            seen = np.ones(len(idx))
            seen[tested] = self.virtual.visibility(p[idx[tested]], n[idx[tested]], d, 0.0, 1)
            near = _near_blocked(seen < 1.0, rv[idx], ru[idx], virtual.shape) & tested
            if np.any(near):
                seen[near] = self.virtual.visibility(
                    p[idx[near]], n[idx[near]], d, source.angular_radius_deg, self.samples
                )
            keep = (seen < 1.0) | touched[idx]
            idx, seen = idx[keep], seen[keep]
            lit = source.irradiance * cos[idx]
            lit *= real_visibility(real_occluder, p[idx], n[idx], d, world_from_cam)
            before[idx] += lit
            after[idx] += lit * seen
        # (a touched pixel no source reaches keeps the SH part's colour: its factor is rho)
        work = np.flatnonzero((after < before) | (touched & (before > 0.0)))
        if not len(work):
            return changed
        # (no change of the SH part: an empty rectangle, ratio 1 and nothing added outside it)
        origin, ratio, delta = (
            (ambient_change.origin, ambient_change.ratio, ambient_change.delta)
            if ambient_change is not None
            else ((0, 0), np.ones((0, 0)), np.zeros((0, 0, 3)))
        )
        _shade_real_pixels(  # `real_surface_factor` and `_indirect_with_source`, per pixel
            rv[work],
            ru[work],
            sh.irradiance_at(ambient_sh, n[work]),
            before[work],
            after[work],
            origin,
            ratio,
            delta,
            color_linear,
            np.asarray(light_rgb, np.float64),
            composite,
            changed,
            TABLE_BASE,
            TABLE_NEXT,
        )
        return changed


@numba.njit(cache=True)
def _shade_real_pixels(
    rows, cols, ambient, before, after, origin, ratio, delta, color_linear, rgb, composite,
    changed, code_base, code_next
):  # fmt: skip
    """composite[rows, cols] = the observed colour times `real_surface_factor` plus the SH
    part's indirect change as `_indirect_with_source` rescales it, encoded; `changed` set
    where either is not the identity. The same float64 operations as those two functions,
    in the same order, on one pixel at a time (no (N, 3) temporaries)."""
    v0, u0 = origin
    h, w = ratio.shape
    for i in range(len(rows)):
        r, c = rows[i] - v0, cols[i] - u0
        inside = 0 <= r < h and 0 <= c < w
        rho = ratio[r, c] if inside else 1.0
        e = max(ambient[i], 0.0)
        lit_before = e + max(before[i], 0.0)
        lit_after = rho * e + max(after[i], 0.0)
        factor = lit_after / max(lit_before, 1e-12) if lit_before > 1e-12 else rho
        any_delta = False
        for k in range(3):
            d = delta[r, c, k] if inside else 0.0
            any_delta |= d != 0.0
            observed = np.float64(color_linear[rows[i], cols[i], k])
            e_k = max(ambient[i], 1e-12) * rgb[k]
            albedo_before = min(observed / max(e_k, 1e-12), 1.0 / math.pi)
            albedo_after = min(observed / max(e_k + before[i] * rgb[k], 1e-12), 1.0 / math.pi)
            if albedo_before > 1e-12:
                d = d * albedo_after / max(albedo_before, 1e-12)
            composite[rows[i], cols[i], k] = counted_code(
                observed * factor + d, code_base, code_next
            )
        changed[rows[i], cols[i]] |= factor != 1.0 or any_delta


def _indirect_with_source(
    delta: np.ndarray,
    observed: np.ndarray,
    ambient: np.ndarray,
    source: np.ndarray,
    light_rgb: np.ndarray,
) -> np.ndarray:
    """(N, 3) the SH renderer's indirect change `delta` with the real surface's albedo
    taken from all of its light: it read rho / pi = observed / (E rgb) (at most 1 / pi),
    which a source's share of the light inflates; rescaled to observed / ((E + S) rgb).
    observed: (N, 3) linear; ambient E, source S: (N,) irradiance (E stands in for the
    SSDO shading the renderer divided by)."""
    rgb = np.asarray(light_rgb, np.float64)
    e = np.maximum(ambient, 1e-12)[:, None] * rgb
    before = np.minimum(observed / np.maximum(e, 1e-12), 1.0 / math.pi)
    after = np.minimum(observed / np.maximum(e + source[:, None] * rgb, 1e-12), 1.0 / math.pi)
    return np.where(before > 1e-12, delta * after / np.maximum(before, 1e-12), delta)


def _near_blocked(
    blocked: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, ...]
) -> np.ndarray:
    """(N,) the pixels (rows, cols) within 2 pixels of one whose centre ray is blocked."""
    import cv2

    mask = np.zeros(shape[:2], np.uint8)
    mask[rows[blocked], cols[blocked]] = 1
    grown = cv2.dilate(mask, np.ones((5, 5), np.uint8)).astype(bool)
    return grown[rows, cols]
