"""Differential rendering of virtual objects into the camera image (section 5.4, eq. 10-15).

The real scene's shading R_d and that of real + virtual R'_d come from the same SSDO
transfer (eq. 6-9) evaluated on two geometry buffers: the filtered real depth G_r, and G_r
with the virtual objects ray cast in under a depth test (`virtual_gbuffer`), so virtual
objects shadow real surfaces, real geometry shadows (and, in front, hides) virtual objects;
the auxiliary buffers get the virtual objects too, so objects out of view still shadow.
Only the pixels that a sample can carry to a virtual object are computed (within
rt_radius_m of an object's bounding sphere): elsewhere the two buffers are the same, and the
composite is the input frame bit for bit.

Real pixels (render_mode "ratio", default): I = I_c R'_d / R_d, exact for a Lambertian
surface; "paper": eq. 13, I_d = I_c (1 + T(R'_d) - T(R_d)), T Reinhard's operator keyed on
each buffer's mean; "paste" is the baseline that only pastes the objects, shaded by the
unshadowed light. Virtual pixels: albedo / pi times R'_d (their own SSDO visibility), whose
unoccluded part is made exact (`unoccluded_correction`, a control variate, looked up in
the renderer's table of its own sampling pattern).
Indirect light (eq. 10-12, 14): the one bounce that SSDO gathers where a direction is
blocked, from the radiance of the blocking surface: the observed image for real surfaces,
the virtual albedo under the estimated light for virtual ones; only the change that the
virtual objects bring (R'_i - R_i, the differential form of eq. 14) is added: I = I_d + I_i
(eq. 15). With render_subsample > 1 ("OursFast") the differential buffers are computed on a
grid and up-sampled bicubically, then Gaussian-filtered (render_blur_radius_px).

Units: `light_sh` is the world-frame luminance SH of the distant light in linear image
units, so that a Lambertian surface of albedo rho with transfer T shows rho / pi * (T . l);
`light_rgb` scales it per channel (white: ones).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numba
import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.pipeline import sh
from arlight.pipeline.aux_buffers import OrthoBuffer
from arlight.pipeline.channels import any_nonzero
from arlight.pipeline.color import LUMA
from arlight.pipeline.config import Config, DiffMode
from arlight.pipeline.glossy import MipPyramid, specular
from arlight.pipeline.horizon import SupportPlane
from arlight.pipeline.probe import ProbeResult
from arlight.pipeline.probe_shading import (
    Glossiness,
    glossiness_of,
    principled_diffuse_weight,
    shade,
)
from arlight.pipeline.radiance_transfer import (
    AuxBufferArrays,
    make_sampling_pattern,
    quadrature_error_table,
    transfer_at_pixels,
    transfer_pair_at_pixels,
)
from arlight.pipeline.srgb_encoding import encode_scaled_where, encode_where, linear_to_srgb_u8
from arlight.pipeline.sun_shadows import (
    AmbientChange,
    CompactSourceShading,
    RealOccluder,
    SourceLight,
    touched_by,
)
from arlight.pipeline.transfer_quadrature import unoccluded_correction
from arlight.pipeline.virtual_gbuffer import VirtualGBuffer, VirtualRaycaster
from arlight.pipeline.virtual_scene import VirtualScene

if TYPE_CHECKING:  # ibl_render imports this module
    from arlight.pipeline.ibl_render import Shading

NEAR_BLOCK_PX = 4  # tile side of `within_reach` (grid pixels)
# a pixel whose depth differs from its grid neighbourhood's by more than this share is on
# another surface: the grid's shading change is not carried onto it (decision 0049)
UPSAMPLE_MAX_RELATIVE_JUMP = 0.05
MIN_SHADING = 1e-6  # R_d below this (linear image units): the ratio is left at 1
# a virtual surface within this of the real depth counts as in front (contact with the ground)
DEPTH_TEST_BIAS_M = 0.005


@dataclass
class RenderInputs:
    """What one frame gives the renderer.

    color: (H, W, 3) uint8 sRGB input frame; color_linear: the same, linear float32;
    depth_m: (H, W) filtered real depth G_r, metres (0 = none); normals_cam: (H, W, 3) unit,
    camera frame (zeros = none); world_from_cam: (4, 4); aux_buffers: the auxiliary
    orthographic buffers of the volume (may be empty); plane: the support plane (used when
    rt_horizon is on, as in RadTransfer); light_sh: (C,) world-frame SH (see module doc);
    light_rgb: (3,) per-channel factor of the light (ones: white); environment: optional
    HDR map whose reflections objects with `mirror` or `metalness` > 0 show (without it every
    object is diffuse); probe: the frame's reflection probe (`probe.ProbeStage`), whose room
    mirror and glossy objects reflect when there is no environment (`probe_shading`).
    """

    color: np.ndarray
    color_linear: np.ndarray
    depth_m: np.ndarray
    normals_cam: np.ndarray
    world_from_cam: np.ndarray
    aux_buffers: list[OrthoBuffer]
    plane: SupportPlane | None
    light_sh: np.ndarray
    light_rgb: np.ndarray = dataclasses.field(default_factory=lambda: np.ones(3))
    environment: EnvironmentMap | None = None
    probe: ProbeResult | None = None
    # compact sources drawn with their hard shadows both ways (sun_shadows), light_sh then
    # being the rest of the light; the reconstruction that shadows them (OcclusionScene)
    sources: list[SourceLight] = dataclasses.field(default_factory=list)
    real_occluder: RealOccluder | None = None


@dataclass(frozen=True)
class EnvironmentMap:
    """An HDR environment for the objects' mirror and glossy reflections (a session lit by
    its 360-degree panorama): pyramid, the mip pyramid (`glossy.mip_pyramid`) of an
    equirectangular radiance map in its own frame, in the units of light_sh;
    map_from_world (3, 3): d_map = R d_world."""

    pyramid: MipPyramid
    map_from_world: np.ndarray


@dataclass(frozen=True)
class _TwoScenes:
    """One frame's real scene and the same with the virtual objects in, as the transfer
    reads them: camera-frame points (H, W, 3) of each, their auxiliary buffers, the
    radiance their blocking surfaces bounce (H, W, 3), the support plane (None unless
    rt_horizon) and the light's colour (3,)."""

    points_r: np.ndarray
    points_c: np.ndarray
    aux_r: AuxBufferArrays | None
    aux_c: AuxBufferArrays | None
    radiance_r: np.ndarray
    radiance_c: np.ndarray
    plane: SupportPlane | None
    light_rgb: np.ndarray


@dataclass
class RenderOutput:
    """composite: (H, W, 3) uint8 sRGB; virtual_mask: (H, W) bool, pixels showing a virtual
    object; region: (H, W) bool, pixels the renderer recomputed (all others are the input's);
    gbuffer: the virtual objects' camera buffer."""

    composite: np.ndarray
    virtual_mask: np.ndarray
    region: np.ndarray
    gbuffer: VirtualGBuffer


class _ShPass(NamedTuple):
    """What `DifferentialRenderer._render_sh` made: the output; with keep_change, what it
    did to the real pixels (None where it changed none); the camera-frame points (H, W, 3)
    of the real scene and of the scene with the objects, and the (K, 3) linear RGB it drew
    the virtual pixels with (np.nonzero(virtual_mask)'s order), where it made them."""

    output: RenderOutput
    ambient_change: AmbientChange | None = None
    points: tuple[np.ndarray, np.ndarray] | None = None
    virtual_linear: np.ndarray | None = None


def reinhard(x: np.ndarray, mean: float, key: float) -> np.ndarray:
    """Reinhard's global operator: x scaled so that `mean` maps to `key`, then x / (1 + x)."""
    scaled = x * (key / max(mean, 1e-12))
    return scaled / (1.0 + scaled)


class DifferentialRenderer:
    """Renders one session's virtual scene into its frames (not thread-safe)."""

    def __init__(self, scene: VirtualScene, camera: PinholeCamera, config: Config):
        self.scene = scene
        self.camera = camera
        self.config = config
        r = config.render
        # the renderer's own sampling: as RadTransfer's, with more samples per direction
        self.transfer_params = dataclasses.replace(
            config.transfer, rt_steps=r.render_steps, rt_subsample=1
        )
        self.pattern = make_sampling_pattern(self.transfer_params, config.seed + 1)
        self.raycaster = VirtualRaycaster(scene)
        self._compact = CompactSourceShading(
            [(o.world_vertices(), o.triangles) for o in scene.objects]
        )
        # per object, made when an environment map first lights them
        self._shadings: list[Shading] | None = None

    @functools.cached_property
    def _quadrature_table(self) -> np.ndarray:
        """`quadrature_error_table` of the renderer's pattern (fixed in the camera frame):
        made on first use, once."""
        return quadrature_error_table(self.pattern, self.transfer_params.sh_bands)

    def render(self, frame: RenderInputs) -> RenderOutput:
        """The composite of one frame (see the module docstring), with the compact
        sources' hard shadows (frame.sources) drawn on it."""
        with_sources = bool(frame.sources) and self.config.render.render_mode is not DiffMode.PASTE
        drawn = self._render_sh(frame, keep_change=with_sources)
        out, ambient_change, points = drawn.output, drawn.ambient_change, drawn.points
        if not with_sources:
            return out
        g = out.gbuffer
        if points is None:
            points = (
                self.camera.unproject(frame.depth_m),
                self.camera.unproject(
                    np.where(out.virtual_mask, g.depth_m, frame.depth_m).astype(np.float32)
                ),
            )
        real_points, points_with_objects = points  # (the second read at virtual pixels only)
        changed = self._compact.apply(
            out.composite,
            out.virtual_mask,
            g.normals_cam,
            self._source_albedo(frame, g, out.virtual_mask, points_with_objects),
            points_with_objects,
            real_points,
            frame.normals_cam,
            frame.world_from_cam,
            frame.light_sh,
            frame.light_rgb,
            frame.sources,
            frame.real_occluder,
            frame.color_linear,
            ambient_change,
            drawn.virtual_linear,
        )
        return RenderOutput(out.composite, out.virtual_mask, out.region | changed, g)

    @functools.cached_property
    def _looks(self) -> list[Glossiness]:
        """Per scene object, made on first use: what the probe's shading does with it."""
        return [glossiness_of(o.material) for o in self.scene.objects]

    @functools.cached_property
    def _diffuse_parts(self) -> tuple[np.ndarray, np.ndarray]:
        """Per scene object, made on first use: the share of its albedo that is diffuse (0
        for a mirror, else 1 - metalness) and whether the probe shades it as glossy."""
        fraction = [
            0.0 if look.kind == 1 else 1.0 - min(max(o.material.metalness, 0.0), 1.0)
            for o, look in zip(self.scene.objects, self._looks, strict=True)
        ]
        return np.array(fraction), np.array([look.kind == 2 for look in self._looks])

    def _source_albedo(
        self, frame: RenderInputs, g: VirtualGBuffer, virtual: np.ndarray, points_cam: np.ndarray
    ) -> np.ndarray:
        """(H, W, 3) the albedo a compact source's light is shaded with on the virtual pixels:
        the diffuse part the SH part drew them with. Where a probe or a panorama reflects the
        light (the source is in what a mirror or glossy object reflects), a mirror has none
        and a metal (1 - metalness) of its albedo, times the principled diffuse weight for a
        glossy object shaded from a probe (`probe_shading.shade`); the plain albedo without
        either. points_cam: (H, W, 3) points (camera frame), read at `virtual` only."""
        if frame.probe is None and frame.environment is None:
            return g.albedo
        fraction, glossy_object = self._diffuse_parts
        vv, uu = np.nonzero(virtual)
        index = g.object_index[vv, uu]
        factor = fraction[index]
        if frame.environment is None:
            glossy = glossy_object[index]
            p = points_cam[vv, uu].astype(np.float64)
            view = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
            n_dot_v = np.abs(np.sum(view * g.normals_cam[vv, uu], axis=1))
            factor = np.where(glossy, factor * principled_diffuse_weight(n_dot_v), factor)
        albedo = g.albedo.copy()
        albedo[vv, uu] *= factor[:, None].astype(albedo.dtype)
        return albedo

    def _diffuse_shown(
        self, frame: RenderInputs, g: VirtualGBuffer, vs: np.ndarray, us: np.ndarray
    ) -> np.ndarray:
        """(K,) bool: which of the virtual pixels (vs, us) show any diffuse light: all of
        them unless a probe or a panorama reflects the light, else those of objects whose
        diffuse share is above zero (not a mirror, metalness below 1)."""
        if frame.probe is None and frame.environment is None:
            return np.ones(len(vs), bool)
        fraction, _ = self._diffuse_parts
        return fraction[g.object_index[vs, us]] > 0.0

    def _render_sh(self, frame: RenderInputs, keep_change: bool = False) -> _ShPass:
        """The composite lit by frame.light_sh (see the module docstring) and, for the
        compact sources drawn after it, what else it made (`_ShPass`)."""
        cam, pose = self.camera, frame.world_from_cam
        r = self.config.render
        g = self.raycaster.camera_gbuffer(cam, pose)
        real_depth = frame.depth_m
        virtual = g.hit & ((real_depth <= 0) | (g.depth_m < real_depth + DEPTH_TEST_BIAS_M))
        composite = np.array(frame.color, dtype=np.uint8, copy=True)
        rect = self.raycaster.screen_rect(cam, pose, margin_m=self.transfer_params.rt_radius_m)
        region = np.zeros(real_depth.shape, bool)
        if rect is None:
            return _ShPass(RenderOutput(composite, virtual, region, g))
        depth_c = np.where(virtual, g.depth_m, real_depth).astype(np.float32)
        normals_c = np.where(virtual[..., None], g.normals_cam, frame.normals_cam)
        points_r = cam.unproject(real_depth)
        points_c = cam.unproject(depth_c)
        aux_r = AuxBufferArrays.from_buffers(frame.aux_buffers, pose) if frame.aux_buffers else None
        aux_c = self._aux_with_virtual(frame.aux_buffers, pose)
        light_rgb = np.asarray(frame.light_rgb, np.float64)
        # radiance of the blocking surfaces: observed for real ones, the virtual albedo
        # under the (unshadowed) estimated light for virtual ones
        radiance_r = frame.color_linear
        radiance_c = radiance_r.copy()
        if np.any(virtual):
            n_world = g.normals_cam[virtual].astype(np.float64) @ pose[:3, :3].T
            e = np.maximum(sh.irradiance_at(frame.light_sh, n_world), 0.0)
            radiance_c[virtual] = g.albedo[virtual] / math.pi * e[:, None] * light_rgb
        if r.render_mode is DiffMode.PASTE:
            composite[virtual] = linear_to_srgb_u8(radiance_c[virtual])
            return _ShPass(RenderOutput(composite, virtual, virtual.copy(), g))
        u0, v0, u1, v1 = rect
        step = r.render_subsample
        gu, gv = _grid_points(u0, u1, step), _grid_points(v0, v1, step)
        guu, gvv = np.meshgrid(gu, gv)
        near = self._near_objects(points_c[gvv, guu], pose)
        real_grid = near & ~virtual[gvv, guu] & (real_depth[gvv, guu] > 0)
        vv_all, uu_all = np.nonzero(virtual)
        p = self.transfer_params
        scenes = _TwoScenes(
            points_r,
            points_c,
            aux_r,
            aux_c,
            radiance_r,
            radiance_c,
            frame.plane if p.rt_horizon else None,
            light_rgb,
        )
        # the real pixels in both scenes at once (their point and normal are the same in
        # both), the virtual pixels in the scene with the objects
        ratio_grid, delta_grid = self._grid_change(frame, scenes, guu, gvv, real_grid)
        weight = np.where(virtual[gvv, guu], 0.0, 1.0)
        # a mirror (or a full metal) under a probe or a panorama shows no diffuse light:
        # its pixels need no transfer (their irradiance is multiplied by zero)
        lit = self._diffuse_shown(frame, g, vv_all, uu_all)
        t_cv = np.zeros((len(uu_all), frame.light_sh.shape[0]))
        b_cv = np.zeros((len(uu_all), radiance_c.shape[2]))
        ok_cv = np.zeros(len(uu_all), bool)
        t_cv[lit], b_cv[lit], ok_cv[lit] = transfer_at_pixels(
            points_c,
            normals_c,
            cam,
            pose,
            self.pattern,
            aux_c,
            p,
            uu_all[lit],
            vv_all[lit],
            radiance_c,
            scenes.plane,
        )
        if not r.render_indirect:
            b_cv = np.zeros_like(b_cv)
        # virtual pixels are shaded absolutely: their unoccluded transfer made exact (real
        # pixels take a ratio of two transfers of the same directions, whose errors cancel)
        t_cv += (
            unoccluded_correction(g.normals_cam[vv_all, uu_all], pose, self._quadrature_table)
            * ok_cv[:, None]
        )
        e_cv = t_cv @ frame.light_sh
        if step == 1:
            # denoising only among the pixels the objects changed, and only there: nothing
            # bleeds onto surfaces they do not touch (a hand in front, the far side of an edge)
            touched = (ratio_grid != 1.0) | any_nonzero(delta_grid)
            weight = weight * touched
        ratio_full, delta_full = self._upsample(
            ratio_grid,
            delta_grid,
            weight,
            rect,
            step,
            r.render_blur_radius_px if step > 1 else r.render_denoise_px,
            (real_depth[gvv, guu], real_depth[v0:v1, u0:u1]),
        )
        if step == 1:
            ratio_full = np.where(touched, ratio_full, 1.0)
            delta_full = np.where(touched[..., None], delta_full, 0.0)
        # virtual pixels: albedo / pi (direct with SSDO visibility + bounce from around)
        e_v = np.maximum(e_cv, 0.0)[:, None] * light_rgb + b_cv
        e_v[~ok_cv] = 0.0
        if frame.environment is None:
            virtual_rgb = g.albedo[vv_all, uu_all] / math.pi * e_v
            if frame.probe is not None:
                self._probe_reflecting(frame.probe, g, vv_all, uu_all, e_v, pose, virtual_rgb)
        else:
            virtual_rgb = self._reflecting(frame.environment, g, vv_all, uu_all, e_v, pose)
        changed = (ratio_full != 1.0) | any_nonzero(delta_full)
        # real pixels: I_c R'_d / R_d plus the indirect change (the virtual ones drawn next)
        encode_scaled_where(
            frame.color_linear[v0:v1, u0:u1],
            ratio_full,
            delta_full,
            changed & ~virtual[v0:v1, u0:u1],
            composite[v0:v1, u0:u1],
        )
        composite[vv_all, uu_all] = linear_to_srgb_u8(virtual_rgb)
        region[v0:v1, u0:u1] = changed
        region |= virtual
        ambient_change = None
        if keep_change:
            real_changed = changed & ~virtual[v0:v1, u0:u1]
            touched = np.zeros(real_depth.shape, bool)
            touched[v0:v1, u0:u1] = real_changed & touched_by(ratio_full, delta_full)
            # (a real pixel it left unchanged has ratio 1 and delta 0 exactly: `changed`)
            ambient_change = AmbientChange((v0, u0), ratio_full, delta_full, touched)
        return _ShPass(
            RenderOutput(composite, virtual, region, g),
            ambient_change,
            (points_r, points_c),
            virtual_rgb,
        )

    def _grid_change(
        self,
        frame: RenderInputs,
        scenes: _TwoScenes,
        grid_u: np.ndarray,
        grid_v: np.ndarray,
        real: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The change the objects bring to the real grid points (grid_u, grid_v: (gh, gw)
        pixel coordinates) selected by `real`: (ratio (gh, gw), delta (gh, gw, 3)); 1 and 0
        at the others."""
        us, vs = grid_u[real], grid_v[real]
        (t_r, b_r), (t_c, b_c), ok = transfer_pair_at_pixels(
            scenes.points_r,
            scenes.points_c,
            frame.normals_cam,
            self.camera,
            frame.world_from_cam,
            self.pattern,
            scenes.aux_r,
            scenes.aux_c,
            self.transfer_params,
            us,
            vs,
            scenes.radiance_r,
            scenes.radiance_c,
            scenes.plane,
        )
        if not self.config.render.render_indirect:
            b_r, b_c = np.zeros_like(b_r), np.zeros_like(b_c)
        e_r, e_c = t_r @ frame.light_sh, t_c @ frame.light_sh
        ratio, delta = self._real_change(frame, e_r, e_c, b_r, b_c, ok, us, vs, scenes.light_rgb)
        ratio_grid = np.ones(grid_u.shape)
        delta_grid = np.zeros((*grid_u.shape, 3))
        ratio_grid[real], delta_grid[real] = ratio, delta
        return ratio_grid, delta_grid

    def _reflecting(
        self,
        env: EnvironmentMap,
        g: VirtualGBuffer,
        vs: np.ndarray,
        us: np.ndarray,
        irradiance_rgb: np.ndarray,
        pose: np.ndarray,
    ) -> np.ndarray:
        """(K, 3) linear radiance of virtual pixels that may reflect `env`: per object
        (`ibl_render.shading_of`: specular weight s = 1 for a mirror, else metalness)
        (1 - s) albedo / pi * irradiance + s albedo * the map seen along the view direction
        mirrored about the normal (one lookup for a mirror, the Phong lobe of its roughness
        for a glossy object)."""
        from arlight.pipeline.ibl_render import shading_of  # it imports this module

        shadings = self._shadings
        if shadings is None:
            shadings = self._shadings = [
                shading_of(o.material, f"virtual object {o.name!r}") for o in self.scene.objects
            ]
        index = g.object_index[vs, us]
        diffuse = np.stack([s.diffuse_rgb for s in shadings])[index]
        spec_rgb = np.stack([s.specular_rgb for s in shadings])[index]
        modes = np.array([s.mode for s in shadings])[index]
        exponents = np.array([s.exponent for s in shadings])[index]
        cam = self.camera
        rays = (
            np.stack([(us - cam.cx) / cam.fx, (vs - cam.cy) / cam.fy, np.ones(len(us))], axis=1)
            @ pose[:3, :3].T
        )
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        normals = g.normals_cam[vs, us].astype(np.float64) @ pose[:3, :3].T
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        mirrored = rays - 2.0 * np.sum(rays * normals, axis=1, keepdims=True) * normals
        seen = specular(env.pyramid, mirrored @ np.asarray(env.map_from_world).T, modes, exponents)
        return diffuse / math.pi * irradiance_rgb + spec_rgb * seen

    def _probe_reflecting(
        self,
        probe: ProbeResult,
        g: VirtualGBuffer,
        vs: np.ndarray,
        us: np.ndarray,
        irradiance_rgb: np.ndarray,
        pose: np.ndarray,
        virtual_rgb: np.ndarray,
    ) -> None:
        """virtual_rgb (K, 3) of the pixels of mirror and glossy objects replaced, in place,
        by their shading from the probe (`probe_shading.shade`)."""
        looks = self._looks
        index = g.object_index[vs, us]
        sel = np.flatnonzero(np.array([look.kind != 0 for look in looks], bool)[index])
        if not len(sel):
            return
        vs, us, index = vs[sel], us[sel], index[sel]
        cam = self.camera
        z = g.depth_m[vs, us].astype(np.float64)
        rays = np.stack([(us - cam.cx) / cam.fx, (vs - cam.cy) / cam.fy, np.ones(len(us))], 1)
        points = (rays * z[:, None]) @ pose[:3, :3].T + pose[:3, 3]
        view = rays @ pose[:3, :3].T
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        normals = g.normals_cam[vs, us].astype(np.float64) @ pose[:3, :3].T
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        virtual_rgb[sel] = shade(
            probe, looks, index, points, normals, view, irradiance_rgb[sel], self.raycaster
        )

    def _near_objects(self, points_cam: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Grid pixels whose point is within rt_radius_m of a virtual object's bounding
        sphere (a sample from there can meet the object)."""
        shape = points_cam.shape[:2]
        pts = points_cam.reshape(-1, 3).astype(np.float64)
        world = pts @ pose[:3, :3].T + pose[:3, 3]
        reach = self.transfer_params.rt_radius_m
        near = (pts[:, 2] > 0) & (self.raycaster.distance_to_spheres(world) <= reach)
        # the exact distance to the meshes only for what the bounding spheres let through,
        # and of those only where the distance at the block's first pixel leaves it open
        near[near] = within_reach(
            world.reshape(*shape, 3), near.reshape(shape), self.raycaster.distance_to_objects, reach
        )
        return near.reshape(shape)

    def _aux_with_virtual(
        self, buffers: list[OrthoBuffer], pose: np.ndarray
    ) -> AuxBufferArrays | None:
        """The auxiliary buffers with the virtual objects depth-tested in."""
        if not buffers:
            return None
        merged = []
        for b in buffers:
            virt = self.raycaster.orthographic_depth(
                b.world_from_buffer, b.resolution, b.pixel_size_m
            )
            depth = np.where(
                (virt > 0) & ((b.depth_m <= 0) | (virt < b.depth_m)), virt, b.depth_m
            ).astype(np.float32)
            merged.append(OrthoBuffer(b.world_from_buffer, depth, b.pixel_size_m, b.name))
        return AuxBufferArrays.from_buffers(merged, pose)

    def _real_change(
        self,
        frame: RenderInputs,
        e_r: np.ndarray,
        e_c: np.ndarray,
        b_r: np.ndarray,
        b_c: np.ndarray,
        ok: np.ndarray,
        us: np.ndarray,
        vs: np.ndarray,
        light_rgb: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per real pixel: (factor on I_c (K,), added linear RGB (K, 3))."""
        r = self.config.render
        lit = ok & (e_r > MIN_SHADING)
        ratio = np.ones(len(e_r))
        # visibility only drops where an object is added: where R'_d > R_d, the object
        # blocked directions in which the band-limited light rings negative; no brightening
        if r.render_mode is DiffMode.RATIO:
            ratio[lit] = np.clip(e_c[lit], 0.0, e_r[lit]) / e_r[lit]
        else:
            # eq. 13 keyed on each buffer's mean over the region
            mean_r = float(np.mean(np.maximum(e_r[lit], 0.0))) if np.any(lit) else 1.0
            mean_c = float(np.mean(np.maximum(e_c[lit], 0.0))) if np.any(lit) else 1.0
            ratio = 1.0 + np.minimum(
                reinhard(np.maximum(e_c, 0.0), mean_c, r.tone_key)
                - reinhard(np.maximum(e_r, 0.0), mean_r, r.tone_key),
                0.0,
            )
            ratio[~ok] = 1.0
        # indirect: the change of the one-bounce irradiance, times albedo / pi; the albedo
        # of a real pixel from the observation, I_c / (R_d / pi), at most 1
        observed = frame.color_linear[vs, us].astype(np.float64)
        rho_over_pi = np.full((len(e_r), 3), r.render_real_albedo / math.pi)
        direct = e_r[:, None] * light_rgb
        good = lit[:, None] & (direct > MIN_SHADING)
        rho_over_pi = np.where(
            good, np.minimum(observed / np.maximum(direct, MIN_SHADING), 1.0 / math.pi), rho_over_pi
        )
        delta = (
            np.where(ok[:, None], rho_over_pi * (b_c - b_r), 0.0)
            if b_r.shape[1]
            else np.zeros((len(e_r), 3))
        )
        return ratio, delta

    @staticmethod
    def _upsample(
        ratio: np.ndarray,
        delta: np.ndarray,
        weight: np.ndarray,
        rect: tuple[int, int, int, int],
        step: int,
        blur_radius: int,
        depths: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Grid buffers -> every pixel of the rect: bicubic, then a Gaussian of the given
        radius, normalised by the up-sampled weights (virtual pixels carry none); at step 1
        only the Gaussian (identity with radius 0).

        depths: (the grid points' depth, the rect's depth) in metres. On a grid (step > 1)
        a pixel keeps no change where the grid's depth, up-sampled the same way, differs
        from its own by more than UPSAMPLE_MAX_RELATIVE_JUMP: it lies on another surface
        than the grid points around it (a hand in front of an object), and the blend would
        carry their shading change onto it."""
        u0, v0, u1, v1 = rect
        if step == 1 and blur_radius == 0:
            return ratio, delta
        size = (ratio.shape[1] * step, ratio.shape[0] * step)
        layers = [(ratio * weight)[..., None], delta * weight[..., None], weight[..., None]]
        edge = depths if step > 1 else None  # the depth test's inputs, on a grid only
        if edge is not None:
            layers.append((edge[0] * weight)[..., None])
        stack = np.concatenate(layers, axis=2).astype(np.float32)
        up = stack if step == 1 else cv2.resize(stack, size, interpolation=cv2.INTER_CUBIC)
        if blur_radius > 0:
            up = cv2.GaussianBlur(up, (2 * blur_radius + 1, 2 * blur_radius + 1), 0)
        up = np.ascontiguousarray(up[: v1 - v0, : u1 - u0])
        ratio_full = np.empty(up.shape[:2], np.float32)
        delta_full = np.empty((*up.shape[:2], 3), np.float32)
        z = np.zeros((0, 0), np.float32) if edge is None else np.ascontiguousarray(edge[1])
        jump = z.dtype.type(UPSAMPLE_MAX_RELATIVE_JUMP)
        _normalised(up, z, jump, ratio_full, delta_full)
        return ratio_full, delta_full


@numba.njit(parallel=True, cache=True)
def _normalised(up, z, jump, ratio, delta):
    """`_upsample`'s last step, one pass over the rect: ratio = up[0] / w and delta = up[1:4]
    / w where w = up[4] > 1e-3 (else 1 and 0); a ratio within 1e-6 of 1 and a delta within
    1e-9 of 0 made exact; with z (the rect's depth; (0, 0): no test) no change where the
    up-sampled grid depth up[5] / w is more than jump * z off z. The same float32 (and z's
    precision) operations as the NumPy expressions it replaced, so the same values."""
    one = np.float32(1.0)
    zero = np.float32(0.0)
    with_depth = z.shape[0] > 0
    for y in numba.prange(up.shape[0]):
        for x in range(up.shape[1]):
            w = up[y, x, 4]
            keep = w > np.float32(1e-3)
            inverse = one / w if keep else zero
            r = up[y, x, 0] * inverse if keep else one
            if abs(r - one) < np.float32(1e-6):
                r = one
            other = False
            if with_depth:
                d = z[y, x]
                other = d > 0 and keep and abs(up[y, x, 5] * inverse - d) > jump * d
            ratio[y, x] = one if other else r
            for c in range(3):
                v = up[y, x, 1 + c] * inverse
                delta[y, x, c] = zero if other or abs(v) < np.float32(1e-9) else v


def _grid_points(start: int, stop: int, step: int) -> np.ndarray:
    """The sub-sampled grid's pixel coordinates along one axis of the rect [start, stop):
    each step-wide cell's centre, the last clipped to the rect."""
    return np.minimum(np.arange(start, stop, step) + step // 2, stop - 1)


def within_reach(
    points: np.ndarray, candidates: np.ndarray, distance, reach: float, block: int = NEAR_BLOCK_PX
) -> np.ndarray:
    """For the candidate grid points, whether distance(point) <= reach, the same answer as
    evaluating `distance` at every one of them, with fewer evaluations.

    points: (H, W, 3) world points (metres); candidates: (H, W) bool; distance: maps (K, 3)
    points to (K,) distances to a set (1-Lipschitz: it changes by at most the distance
    moved). Evaluated first at each block x block tile's top-left point (if a candidate);
    a candidate whose distance from that anchor is d_q +/- |p - q| entirely on one side of
    reach needs no evaluation of its own. The candidates left open are tried again with
    tiles half the size (their new anchors evaluated), down to tiles of 2; the rest, and
    tiles without an anchor, are evaluated. Returns (number of candidates,) bool, in
    candidates' row-major order.
    """
    rows, cols = np.nonzero(candidates)
    if len(rows) < 4 * block * block:  # too few for the anchors to pay
        return distance(points[rows, cols]) <= reach
    known = np.full(candidates.shape, np.nan)  # distance where evaluated
    result = np.zeros(len(rows), bool)
    open_ = np.arange(len(rows))
    while block > 1 and len(open_):
        r, c = rows[open_], cols[open_]
        ar, ac = r // block * block, c // block * block
        new = candidates[ar, ac] & np.isnan(known[ar, ac])
        if np.any(new):
            flat = np.unique(ar[new] * candidates.shape[1] + ac[new])
            qr, qc = np.divmod(flat, candidates.shape[1])
            known[qr, qc] = distance(points[qr, qc])
        d_q = known[ar, ac]
        moved = np.linalg.norm(points[r, c] - points[ar, ac], axis=1)
        inside = d_q + moved <= reach
        result[open_[inside]] = True
        open_ = open_[~(inside | (d_q - moved > reach))]  # includes NaN: no anchor
        block //= 2
    if len(open_):
        result[open_] = distance(points[rows[open_], cols[open_]]) <= reach
    return result


def luminance_light_rgb(sh_rgb: np.ndarray | None) -> np.ndarray:
    """(3,) per-channel factor of the light from per-channel SH (band 0), luminance 1; ones
    (white, the paper's assumption) without them."""
    if sh_rgb is None:
        return np.ones(3)
    dc = np.maximum(np.asarray(sh_rgb, np.float64)[:, 0], 0.0)
    lum = float(LUMA @ dc)
    return dc / lum if lum > 0 else np.ones(3)


__all__ = [
    "DifferentialRenderer",
    "EnvironmentMap",
    "RenderInputs",
    "RenderOutput",
    "encode_where",
    "linear_to_srgb_u8",
    "luminance_light_rgb",
    "reinhard",
]
