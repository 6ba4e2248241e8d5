"""One session's light-estimation pipeline: frames in, lighting out.

Data flow: docs/architecture.md, "Data flow".

Stages, named as the rows of the paper's table 1: Input, Reconstruct, Surface, DynGeo,
RadTransfer, LightEst, Rendering (differential rendering of the virtual scene; skipped,
at no cost, when there is none).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import logging
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.checks import CheckError, check_finite, check_image, check_rigid, depth_metres
from arlight.core.contracts import TrackingDiagnostics
from arlight.core.frames import (
    Diagnostics,
    FrameInput,
    FrameResult,
    RenderLight,
    compact_lights,
)
from arlight.pipeline import sh
from arlight.pipeline.channels import any_nonzero
from arlight.pipeline.color import intensity_from_rgb, luminance, srgb_to_linear
from arlight.pipeline.compact_light import CompactFit
from arlight.pipeline.config import Config, RtMethod
from arlight.pipeline.depth_filter import backend_for_device, filter_depth, normals_from_depth
from arlight.pipeline.horizon import SupportPlane, support_plane
from arlight.pipeline.light_estimation import (
    LightEstimate,
    fittable_colour,
)
from arlight.pipeline.light_stage import LightFrame, LightStage
from arlight.pipeline.object_space_transfer import ObjectSpaceTransfer, OcclusionScene
from arlight.pipeline.probe import (
    DistantLight,
    ProbeResult,
    ProbeSettings,
    ProbeStage,
    objects_centre,
)
from arlight.pipeline.probe_shading import is_reflective
from arlight.pipeline.radiance_transfer import (
    AuxBufferArrays,
    TransferSamples,
    compute_transfer,
    interpolated_samples,
    make_sampling_pattern,
    quadrature_error_table,
    random_pixels,
    transfer_at_pixels,
    with_exact_unoccluded,
)
from arlight.pipeline.rendering import (
    DifferentialRenderer,
    EnvironmentMap,
    RenderInputs,
    RenderOutput,
    luminance_light_rgb,
)
from arlight.pipeline.runtime import require_device
from arlight.pipeline.segmentation import SEGMENT_K, SEGMENT_MIN_SIZE_PX, material_segments
from arlight.pipeline.still import StillCamera
from arlight.pipeline.sun_shadows import SourceLight
from arlight.pipeline.virtual_scene import VirtualScene, resolve_anchors
from arlight.pipeline.volume import upsample_depth
from arlight.pipeline.work_resolution import (
    enlarge_geometry,
    reduce_depth,
    reduce_frame,
    reduce_image,
    work_scale,
)

log = logging.getLogger(__name__)

STAGES = (
    "Input",
    "Reconstruct",
    "Surface",
    "DynGeo",
    "RadTransfer",
    "LightEst",
    "Probe",  # the reflection probe (pipeline/probe.py): 0 where nothing asks for one
    "Rendering",
)
# RadTransfer computes (or interpolates) the transfer at most at this many pixels per sample
# LightEst may use (light_max_samples): a margin for the clipped, dark and transfer-less ones
# it then leaves out (typically under 10 %)
CANDIDATES_PER_SAMPLE = 1.25
# the exact transfer (rt_subsample 1) is computed only at pixels whose colour the fit can
# use, so its margin is for the few fully occluded ones (docs/decisions/0047-fittable-pixels.md)
EXACT_CANDIDATES_PER_SAMPLE = 1.05


def transfer_pixels(config: Config) -> int:
    """The most pixels RadTransfer gives a transfer (computed or interpolated) for the fit:
    a margin over light_max_samples, small where the exact transfer is computed only at
    pixels whose colour the fit can use (SSDO at every pixel)."""
    exact = config.transfer.rt_subsample == 1 and config.transfer.rt_method is not RtMethod.RAYCAST
    margin = EXACT_CANDIDATES_PER_SAMPLE if exact else CANDIDATES_PER_SAMPLE
    return int(margin * config.estimation.light_max_samples)


class FrameError(CheckError):
    """A frame that cannot be processed; the message names the field and the limit."""


@dataclass(frozen=True)
class ValidFrame:
    """A frame that passed `validate_frame`: color (H, W, 3) uint8 RGB; depth_m (H, W)
    float32 metres, 0 = missing (NaN, inf, negative, > 100 m -> 0); pose (4, 4) rigid
    world_from_cam float64 or None."""

    color: np.ndarray
    depth_m: np.ndarray
    pose: np.ndarray | None


def _no_checkpoint(stage: str) -> None:
    pass


def validate_frame(frame: FrameInput, camera: PinholeCamera) -> ValidFrame:
    """The pipeline's one edge (arlight.core.checks); FrameError naming the field otherwise.

    Depth is converted to metres here, once (uint16 with frame.depth_scale, or float metres
    without); the pose must be rigid within the wire's tolerance (1e-3).
    """
    size = (camera.width, camera.height)
    try:
        color = check_image(
            frame.color,
            "color",
            channels=3,
            dtype=np.uint8,
            size=size,
            size_of="the camera calibration's",
        )
        check_image(frame.depth, "depth", size=size, size_of="the camera calibration's")
        depth = depth_metres(frame.depth, frame.depth_scale, "depth")
        pose = None if frame.pose is None else check_rigid(frame.pose, "pose")
        check_finite(frame.timestamp, "timestamp")
    except CheckError as exc:
        raise FrameError(exc.field, exc.message) from None
    return ValidFrame(color, depth, pose)


@contextmanager
def _stage(timings: dict[str, float], name: str):
    """Adds the wall-clock milliseconds of the block to timings[name]."""
    t0 = time.perf_counter()
    yield
    timings[name] = timings.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


@dataclass
class _Geometry:
    """The DynGeo stage's output: G_r of the paper and what is derived from it."""

    depth_m: np.ndarray  # (H, W) float32 filtered depth, 0 = missing
    normals: np.ndarray  # (H, W, 3) float32 camera frame, zeros where unknown
    points: np.ndarray  # (H, W, 3) float32 camera frame
    plane: SupportPlane | None


@dataclass
class _Front:
    """What a frame's Input .. RadTransfer leave for its LightEst, probe and rendering."""

    timestamp: float
    full: ValidFrame  # the input frame at its own size (the composite's)
    full_linear: np.ndarray  # (H, W, 3) its linear colour
    color_linear: np.ndarray  # (h, w, 3) linear colour at the work resolution
    pose: np.ndarray
    aux_buffers: list
    geometry: _Geometry
    transfer: TransferSamples
    labels: np.ndarray | None
    render_light: RenderLight | None
    timings: dict[str, float]
    diagnostics: Diagnostics
    # the reconstruction the compact sources' shadows are tested and drawn against, taken
    # right after this frame's fusion (None without compact sources): `_back` reads no volume
    # (what overlapping then gains: docs/results/speed.md, "compact sources on")
    occluder: OcclusionScene | None = None


def smooth_depth_for_normals(depth_m: np.ndarray, window: int) -> np.ndarray:
    """Validity-weighted box mean of depth over `window` pixels, for normals only.

    One-pixel differences of sensor depth give normals that are mostly noise (Kinect noise at
    2-3 m is as large as the pixel footprint), and least squares on such normals explains
    albedo texture as shading. Pixels whose mean departs from their own depth by > 3 % (depth
    edges) are left out (0).
    """
    if window <= 1:
        return depth_m
    valid = (depth_m > 0).astype(np.float32)
    num = cv2.boxFilter(
        depth_m, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    den = cv2.boxFilter(
        valid, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    mean = np.where(den > 0, num / np.maximum(den, 1e-6), 0.0)
    keep = (depth_m > 0) & (np.abs(mean - depth_m) < 0.03 * depth_m)
    return np.where(keep, mean, 0.0).astype(np.float32)


@functools.cache
def _side_work() -> concurrent.futures.ThreadPoolExecutor:
    """The process's worker threads for work a frame can do beside its main thread (one
    per core: several sessions' pipelines may ask at once)."""
    return concurrent.futures.ThreadPoolExecutor(
        max_workers=os.cpu_count() or 2, thread_name_prefix="arlight-side"
    )


class Pipeline:
    """Holds one session's state (volume, pose, temporal filter); see docs/architecture.md.

    config: all parameters (Config.from_preset); camera: intrinsics of the (registered)
    colour and depth images; scene: virtual objects to render into each frame (the
    composite of FrameResult; None or empty: nothing is rendered and the composite is left
    None, meaning the input frame). Not thread-safe (pipeline.runtime).
    """

    def __init__(self, config: Config, camera: PinholeCamera, scene: VirtualScene | None = None):
        require_device(config.device)  # a clear error, not Open3D's, when there is no GPU
        self.config = config
        self.camera = camera
        # the frame as analysed (work_width): its camera, and the image-space sub-samplings
        # (given in input pixels) in its own pixels
        self.work_scale = work_scale(camera.width, config.work_width)
        self.work_camera = camera.reduced(self.work_scale)
        self._transfer_params = dataclasses.replace(
            config.transfer, rt_subsample=max(1, config.transfer.rt_subsample // self.work_scale)
        )
        self.requested_scene = scene  # as given; `scene` holds the objects as placed
        self.scene = scene if scene else None
        # the renderer of the placed objects; anchored ones wait for a support plane
        self._renderer: DifferentialRenderer | None = None
        if self.scene is not None and not self.scene.anchored:
            self._renderer = DifferentialRenderer(self.scene, camera, config)
        self.last_render: tuple[RenderInputs, RenderOutput] | None = None
        self.pattern = make_sampling_pattern(config.transfer, config.seed)
        self.frames_processed = 0
        self._frames_begun = 0  # frames whose Reconstruct ran (the next may run ahead)
        self._volume = None
        if config.volume.use_volume:
            from arlight.pipeline.reconstruction import VolumeReconstruction

            # the auxiliary buffers serve SSDO's visibility and the virtual objects' shadows
            # only: without either nothing reads them, and they are not rendered
            aux_read = (
                config.transfer.visibility and config.transfer.rt_method is RtMethod.SSDO
            ) or self.scene is not None
            self._volume = VolumeReconstruction.from_config(
                config if aux_read else config.replace(aux_buffers=False), self.work_camera
            )
        self._pose = np.eye(4)
        # rt_method raycast: the session's ray-casting scene, rebuilt as the volume grows
        self._raycaster = (
            ObjectSpaceTransfer(config.aux.aux_update_interval)
            if config.transfer.rt_method is RtMethod.RAYCAST
            else None
        )
        # a camera held still over an unchanged depth image: DynGeo and RadTransfer of the
        # last frame that made them serve again (pipeline.still)
        self._still = StillCamera(config.reuse, with_depth=True)
        self._last_transfer: tuple[_Geometry, TransferSamples] | None = None
        # LightEst's session state: the temporal filter, the support plane's up, the
        # compact sources (pipeline/light_stage.py)
        self.light = LightStage(config, self.work_camera.width, self._raycaster)
        # the reflection probe (pipeline/probe.py): made each frame for mirror and glossy
        # objects, or for every frame once probe_wanted is set (`arlight estimate
        # --probe-out`); probe_point: where (world, metres; None: the objects' centre)
        self.probe_wanted = False
        self.probe_point: np.ndarray | None = None
        self.last_probe: ProbeResult | None = None
        self._probe: ProbeStage | None = None

    @functools.cached_property
    def _quadrature_table(self) -> np.ndarray:
        """The session's `quadrature_error_table` (rt_exact_unoccluded; its pattern is fixed
        in the camera frame: made on first use, once)."""
        return quadrature_error_table(self.pattern, self.config.transfer.sh_bands)

    @property
    def last_compact(self) -> CompactFit | None:
        """The last frame's compact sources (None without compact sources or before a
        frame): LightStage.last_compact."""
        return self.light.last_compact

    @property
    def volume_blocks(self) -> int:
        """Voxel blocks allocated in the session's volume so far (0 without a volume)."""
        return 0 if self._volume is None else int(self._volume.num_blocks)

    def process(
        self,
        frame: FrameInput,
        render_light: RenderLight | None = None,
        checkpoint: Callable[[str], None] | None = None,
    ) -> FrameResult:
        """Estimate the lighting of one frame. Raises FrameError on malformed input.

        render_light: an optional `RenderLight` (radiance SH in the WORLD frame, and the
        panorama's HDR map for mirror and glossy objects) that renders the virtual objects
        instead of this frame's estimate (a session lit by its 360-degree panorama,
        `light_source` "panorama"); the estimate is still made and returned. A plain
        (sh, sh_rgb[, environment]) tuple is read as a RenderLight.

        checkpoint: optional, called with each stage's name before it starts (not before
        Input), and with "LightEst" before each robust iteration; whatever it raises abandons
        the frame there (the server's per-frame deadline). Nothing else is interrupted; the
        session's state keeps what the finished stages did (the volume may hold the
        abandoned frame's depth)."""
        check = checkpoint or _no_checkpoint
        return self._back(self._front(frame, render_light, check, self.light.light_world), check)

    def process_overlapped(
        self, frames: Iterable[FrameInput], render_light: RenderLight | None = None
    ) -> Iterator[FrameResult]:
        """`process` of each frame in turn, the next frame's Input .. RadTransfer running on
        a thread of its own while this one's LightEst, probe and rendering run (LightEst
        keeps one core busy, the stages before it two): more frames a second for a frame
        of latency (docs/decisions/0042-overlapped-frames.md). The results differ from
        `process`'s only in that a frame's auxiliary "light" buffer points where the frame
        before last put the light, not the last. The back half reads no volume: the compact
        sources' occluder is taken in the front half, after the frame's fusion. FrameError
        is raised when the bad frame's result is due."""
        # leaving the block (also when the consumer stops early) waits for a running front
        with concurrent.futures.ThreadPoolExecutor(1, "arlight-front") as front_thread:
            pending: concurrent.futures.Future[_Front] | None = None
            for frame in frames:
                # the light as it stands now (before this frame's back half): the same
                # whatever the threads' timing
                ahead = front_thread.submit(
                    self._front, frame, render_light, _no_checkpoint, self.light.light_world
                )
                if pending is not None:
                    yield self._back(pending.result(), _no_checkpoint)
                pending = ahead
            if pending is not None:
                yield self._back(pending.result(), _no_checkpoint)

    def _front(
        self,
        frame: FrameInput,
        render_light: RenderLight | tuple | None,
        check: Callable[[str], None],
        light_world: np.ndarray | None,
    ) -> _Front:
        """Input, Reconstruct, Surface, DynGeo and RadTransfer (with the material segments);
        light_world: towards the light (world) that the auxiliary "light" buffer faces."""
        if render_light is not None and not isinstance(render_light, RenderLight):
            render_light = RenderLight(*render_light)
        if render_light is not None and not isinstance(
            render_light.environment, (EnvironmentMap, type(None))
        ):
            got = type(render_light.environment).__name__
            raise FrameError(
                "render_light.environment", f"a rendering.EnvironmentMap or None, not {got}"
            )
        timings: dict[str, float] = {}
        diagnostics: Diagnostics = {}
        with _stage(timings, "Input"):
            full = validate_frame(frame, self.camera)
            full_linear = srgb_to_linear(full.color)
            work = reduce_frame(full.color, full_linear, full.depth_m, self.work_scale)
            valid = ValidFrame(work.color, work.depth_m, full.pose)  # at the work resolution
            intensity = intensity_from_rgb(valid.color)
            color_linear = work.color_linear
        check("Reconstruct")
        pose, depth_volume, aux_buffers, tracked = self._reconstruct(
            valid, timings, diagnostics, light_world
        )
        self._frames_begun += 1
        check("DynGeo")
        with _stage(timings, "DynGeo"):  # the test of a still camera costs ~1 ms
            reused = (
                self._last_transfer
                if self._last_transfer is not None
                and tracked
                and self._still.may_reuse(pose, valid.depth_m)
                else None
            )
        if reused is not None:
            geometry, transfer = reused
            timings["RadTransfer"] = 0.0
            diagnostics["reused"].update({"DynGeo": True, "RadTransfer": True})
            labels = self._segments(color_linear, geometry)
        else:
            geometry, transfer, labels = self._geometry_and_transfer(
                valid, depth_volume, intensity, color_linear, pose, aux_buffers, timings, check
            )
            self._last_transfer = (geometry, transfer)
            self._still.did_work(pose, valid.depth_m)
        occluder = None
        if self.config.estimation.compact_sources > 0:
            check("LightEst")
            with _stage(timings, "LightEst"):  # the compact sources' part, timed as theirs
                occluder = self.light.compact().occluder(geometry.points, self._volume)
        return _Front(
            float(frame.timestamp),
            full,
            full_linear,
            color_linear,
            pose,
            aux_buffers,
            geometry,
            transfer,
            labels,
            render_light,
            timings,
            diagnostics,
            occluder,
        )

    def _back(self, front: _Front, check: Callable[[str], None]) -> FrameResult:
        """LightEst (with the compact sources and the temporal filter), Probe, Rendering."""
        geometry, transfer, pose = front.geometry, front.transfer, front.pose
        timings, diagnostics = front.timings, front.diagnostics
        check("LightEst")
        with _stage(timings, "LightEst"):
            plane = geometry.plane
            up_world = pose[:3, :3] @ plane.up if plane is not None else None
            light = self.light.run(
                LightFrame(
                    transfer,
                    geometry.points,
                    geometry.normals,
                    up_world,
                    front.color_linear,
                    front.labels,
                    pose,
                    front.occluder,
                ),
                check,
                diagnostics,
            )
            coeffs, estimate = light.coeffs, light.estimate
        composite = None
        check("Probe")
        with _stage(timings, "Probe"):
            probe = self._make_probe(
                front.color_linear,
                geometry,
                pose,
                coeffs,
                estimate,
                front.render_light,
                diagnostics,
            )
        if self.scene is None:
            timings["Rendering"] = 0.0
        else:
            check("Rendering")
            with _stage(timings, "Rendering"):
                composite = self._render(
                    front.full,
                    front.full_linear,
                    geometry,
                    pose,
                    front.aux_buffers,
                    coeffs,
                    estimate,
                    front.render_light,
                    probe,
                    front.occluder,
                )
        self.frames_processed += 1
        diagnostics.update(self.light.diagnostics_of(light))
        rotation = pose[:3, :3]
        return FrameResult(
            timestamp=front.timestamp,
            sh=coeffs,
            sh_camera=sh.rotate(coeffs, rotation.T),
            dominant_direction_world=light.direction_world,
            dominant_direction_camera=rotation.T @ light.direction_world,
            intensity=light.intensity,
            confidence=light.confidence,
            pose=pose.copy(),
            sh_rgb=estimate.sh_rgb,
            composite=composite,
            timings_ms=timings,
            diagnostics=diagnostics,
            compact_sources=compact_lights(
                () if self.last_compact is None else self.last_compact.sources, rotation
            ),
        )

    def _geometry_and_transfer(
        self,
        valid: ValidFrame,
        depth_volume: np.ndarray | None,
        intensity: np.ndarray,
        color_linear: np.ndarray,
        pose: np.ndarray,
        aux_buffers: list,
        timings: dict[str, float],
        check: Callable[[str], None],
    ) -> tuple[_Geometry, TransferSamples, np.ndarray | None]:
        """DynGeo and RadTransfer, and LightEst's material segments beside RadTransfer."""
        with _stage(timings, "DynGeo"):
            geometry = self._dynamic_geometry(valid.depth_m, depth_volume, intensity)
        # LightEst's material segments need only colour and geometry: they are made beside
        # RadTransfer (OpenCV's segmentation runs on one core, outside the interpreter lock,
        # while the transfer's NumPy steps leave the other idle)
        check("RadTransfer")
        segments = _side_work().submit(self._segments, color_linear, geometry)
        try:
            with _stage(timings, "RadTransfer"):
                transfer = self._transfer(geometry, color_linear, pose, aux_buffers)
        except BaseException:
            concurrent.futures.wait([segments])  # nothing of this frame outlives it
            raise
        return geometry, transfer, segments.result()

    def _render(
        self,
        valid: ValidFrame,
        color_linear: np.ndarray,
        geometry: _Geometry,
        pose: np.ndarray,
        aux_buffers: list,
        coeffs: np.ndarray,
        estimate: LightEstimate,
        render_light: RenderLight | None = None,
        probe: ProbeResult | None = None,
        occluder: OcclusionScene | None = None,
    ) -> np.ndarray | None:
        """Rendering: the composite (H, W, 3) uint8 of the placed virtual objects, or None
        (the input) while none is placed. The estimate knows albedo x light only (its mean
        albedo is 1): the light is scaled by pi / render_real_albedo into image units;
        occluder: the reconstruction that shadows the compact sources (`_Front.occluder`)."""
        if self._renderer is None:
            self._place_anchored(geometry, pose)
            if self._renderer is None:
                return None
        # the estimate, or an outside light (the panorama's), as many coefficients as it
        light, light_rgb = self._render_light(coeffs, estimate, render_light)
        environment = cast(  # its type checked in process
            "EnvironmentMap | None", None if render_light is None else render_light.environment
        )
        depth_m, normals = enlarge_geometry(
            geometry.depth_m, geometry.normals, self.work_scale, valid.depth_m.shape
        )
        inputs = RenderInputs(
            valid.color,
            color_linear,
            depth_m,
            normals,
            pose,
            list(aux_buffers),
            geometry.plane,
            light,
            light_rgb,
            environment,
            probe,
        )
        drawn = self._with_compact_sources(inputs, occluder) if render_light is None else inputs
        output = self._renderer.render(drawn)
        self.last_render = (inputs, output)  # the frame's light as the SH holds it
        return output.composite

    def _with_compact_sources(
        self, inputs: RenderInputs, occluder: OcclusionScene | None
    ) -> RenderInputs:
        """The inputs that draw the frame's compact sources with their shadows
        (compact_render): the light fitted beside them as light_sh, the sources, and the
        reconstruction that shadows them (`occluder`, taken by `_front`); `inputs` itself
        where there is none."""
        fit = self.last_compact
        if fit is None or not fit.sources or not self.config.estimation.compact_render:
            return inputs
        scale = math.pi / self.config.render.render_real_albedo
        # the light fitted beside the sources (this frame's: the filter holds the SH's)
        ambient = np.zeros(len(inputs.light_sh))
        m = min(len(ambient), len(fit.ambient))
        ambient[:m] = scale * fit.ambient[:m]
        sources = [  # their colour: the light's (inputs.light_rgb), as the SH's
            SourceLight(s.direction, scale * s.intensity, np.ones(3), s.angular_radius_deg)
            for s in fit.sources
        ]
        return dataclasses.replace(
            inputs,
            light_sh=ambient,
            sources=sources,
            real_occluder=occluder,
        )

    def _render_light(
        self, coeffs: np.ndarray, estimate: LightEstimate, render_light: RenderLight | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(world luminance SH in linear image units, (3,) colour) that lights the objects."""
        if render_light is None:
            light = np.asarray(coeffs, np.float64) * (
                math.pi / self.config.render.render_real_albedo
            )
            return light, luminance_light_rgb(estimate.sh_rgb)
        n = len(coeffs)
        light = np.zeros(n)
        given = np.asarray(render_light.sh, np.float64)[:n]
        light[: len(given)] = given
        return light, luminance_light_rgb(render_light.sh_rgb)

    def _make_probe(
        self,
        color_linear: np.ndarray,
        geometry: _Geometry,
        pose: np.ndarray,
        coeffs: np.ndarray,
        estimate: LightEstimate,
        render_light: RenderLight | None,
        diagnostics: Diagnostics,
    ) -> ProbeResult | None:
        """Probe: the frame's reflection probe, where one is wanted (mirror or glossy objects
        placed, or probe_wanted), else None; its notes to diagnostics["probe"]."""
        r = self.config.render
        self.last_probe = None
        if not r.probe:
            return None
        if self.scene is not None and self._renderer is None:
            self._place_anchored(geometry, pose)
        renderer, scene = self._renderer, self.scene
        placed = renderer is not None and scene is not None
        reflective = (
            renderer is not None
            and scene is not None
            and any(is_reflective(o.material) for o in scene.objects)
        )
        if not (reflective or self.probe_wanted):
            return None
        if self.probe_point is not None:
            point = self.probe_point
        elif renderer is not None and placed:
            point = objects_centre(renderer.raycaster.bounding_spheres())
        else:
            return None  # asked for, but no point yet (anchored objects not placed)
        if self._probe is None:
            self._probe = ProbeStage(
                ProbeSettings(
                    r.probe_size,
                    r.probe_room,
                    r.probe_cells,
                    r.probe_cell_m,
                    memory=self._volume is not None,
                    sun=r.probe_sun,
                    window=r.probe_sh_window,
                ),
                self.work_camera,
            )
        notes = self._probe.fuse(point, geometry.depth_m, color_linear, pose)
        light, light_rgb = self._render_light(coeffs, estimate, render_light)
        environment = None if render_light is None else render_light.environment
        probe = self._probe.probe(point, pose, DistantLight(light, light_rgb, environment), notes)
        diagnostics["probe"] = probe.diagnostics
        self.last_probe = probe
        return probe

    def _place_anchored(self, geometry: _Geometry, pose: np.ndarray) -> None:
        """Resolve anchored objects on this frame's support plane; build the renderer once
        every object is placed."""
        if self.scene is None:  # (the caller renders only a scene)
            return
        plane = geometry.plane
        if plane is None:
            plane = support_plane(geometry.normals, geometry.points)
        if plane is None:
            return
        self.scene = resolve_anchors(self.scene, plane.up, plane.offset, pose, self.camera)
        if not self.scene.anchored:
            self._renderer = DifferentialRenderer(self.scene, self.camera, self.config)

    def _reconstruct(
        self,
        valid: ValidFrame,
        timings: dict[str, float],
        diagnostics: Diagnostics,
        light_world: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray | None, list, bool]:
        """Reconstruct + Surface: (pose, D_v or None, aux buffers, tracked: the frame was
        tracked or its pose given, else the last pose is kept); tracking diagnostics and
        `reused` ({stage: bool}: a still camera's stage outputs taken from an earlier frame);
        the "light" aux buffer faces light_world."""
        diagnostics["reused"] = {"Surface": False, "DynGeo": False, "RadTransfer": False}
        depth_volume, aux_buffers = None, []
        if self._volume is None:
            timings["Reconstruct"] = timings["Surface"] = 0.0
            tracked = valid.pose is not None or self._frames_begun == 0
            pose = valid.pose if valid.pose is not None else self._pose
            tracking: TrackingDiagnostics = {
                "ok": tracked,
                "reason": ""
                if tracked
                else "no volume (use_volume false) and no pose: the last pose is kept",
            }
        else:
            surface = self._volume.process_validated(valid.depth_m, valid.pose, light_world)
            timings["Reconstruct"] = surface.timings_ms.get("Reconstruct", 0.0)
            timings["Surface"] = surface.timings_ms.get("Surface", 0.0)
            pose, depth_volume, aux_buffers = (
                surface.pose,
                surface.depth_volume_m,
                surface.aux_buffers,
            )
            tracked = bool(surface.tracking.ok)
            tracking = cast(TrackingDiagnostics, surface.tracking.to_dict())
            # a still camera: fusion skipped, the last frame's cast and aux buffers reused
            diagnostics["reused"]["Surface"] = surface.reused
        self._pose = pose
        diagnostics["tracking_ok"] = tracked
        diagnostics["tracking"] = tracking
        return pose, depth_volume, aux_buffers, tracked

    def _dynamic_geometry(
        self, depth_m: np.ndarray, depth_volume: np.ndarray | None, intensity: np.ndarray
    ) -> _Geometry:
        """DynGeo: the filter chain (eq. 1-5), normals, points and the support plane."""
        c = self.config
        windows = c.filter.at_width(self.work_camera.width)
        depth_filtered = self._filtered_depth(depth_m, depth_volume, intensity)
        normals = normals_from_depth(
            smooth_depth_for_normals(depth_filtered, windows.normal_window), self.work_camera
        )
        points = self.work_camera.unproject(depth_filtered)
        plane = None
        if (
            c.transfer.rt_horizon
            or c.estimation.horizon_prior > 0
            or c.estimation.segment_split_ground
        ):
            plane = support_plane(normals, points)
        return _Geometry(depth_filtered, normals, points, plane)

    def _filtered_depth(
        self, depth_m: np.ndarray, depth_volume: np.ndarray | None, intensity: np.ndarray
    ) -> np.ndarray:
        """The filter chain's depth at the work resolution; with `filter_width` it runs on
        the work image reduced (windows scaled to it) and its depth is enlarged back."""
        c = self.config
        scale = work_scale(self.work_camera.width, c.filter.filter_width)
        if scale > 1:
            depth_m = reduce_depth(depth_m, scale)
            if depth_volume is not None:
                depth_volume = reduce_depth(depth_volume, scale)
            intensity = reduce_image(intensity, depth_m.shape)
        windows = c.filter.at_width(depth_m.shape[1])
        filtered, _ = filter_depth(
            depth_m, depth_volume, intensity, windows, backend=backend_for_device(c.device)
        )
        if scale == 1:
            return filtered
        shape = (self.work_camera.height, self.work_camera.width)
        return upsample_depth(filtered, scale, shape)

    def _transfer(
        self, geometry: _Geometry, color_linear: np.ndarray, pose: np.ndarray, aux_buffers: list
    ) -> TransferSamples:
        """RadTransfer: `_sampled_transfer`, its unoccluded part made exact
        (rt_exact_unoccluded; not with rt_horizon, where below the horizon is the ground's,
        the bounce term's, not the light's)."""
        samples = self._sampled_transfer(geometry, color_linear, pose, aux_buffers)
        p = self._transfer_params
        if not p.rt_exact_unoccluded or p.rt_horizon:
            return samples
        return with_exact_unoccluded(samples, geometry.normals, pose, self._quadrature_table)

    def _sampled_transfer(
        self, geometry: _Geometry, color_linear: np.ndarray, pose: np.ndarray, aux_buffers: list
    ) -> TransferSamples:
        """The transfer (eq. 6-9, or rays against the surface with rt_method "raycast") where
        the light estimate needs it: at most CANDIDATES_PER_SAMPLE x light_max_samples pixels
        with geometry, chosen at random (seeded), the rest of the image being work nothing
        reads. At every pixel (rt_subsample 1) the transfer is computed at those pixels
        only; sub-sampled (OursFast) it is computed on the grid and interpolated to them
        (rt_upsample; without it the grid points themselves are the samples)."""
        p = self._transfer_params
        lum = luminance(color_linear) if p.rt_bounce else None
        plane = geometry.plane if p.rt_horizon else None
        budget = transfer_pixels(self.config)
        seed = self.config.seed
        has_geometry = (geometry.depth_m > 0) & any_nonzero(geometry.normals)

        def at_pixels(us: np.ndarray, vs: np.ndarray) -> tuple:
            """transfer_at_pixels of this frame (SSDO; `aux` is set below before a call)."""
            return transfer_at_pixels(
                geometry.points,
                geometry.normals,
                self.work_camera,
                pose,
                self.pattern,
                aux,
                p,
                us,
                vs,
                None if lum is None else lum[..., None],
                plane,
            )

        if self._raycaster is not None:  # rt_method raycast
            grid = self._raycaster.compute(
                geometry.points,
                geometry.normals,
                self.work_camera,
                pose,
                self.pattern,
                p,
                lum,
                plane,
                self._volume,
            )
        else:
            aux = AuxBufferArrays.from_buffers(aux_buffers, pose) if aux_buffers else None
            if p.rt_subsample == 1:  # exact: only at pixels whose colour the fit can use
                fittable, clipped = fittable_colour(color_linear, has_geometry)
                candidates = has_geometry & fittable
                # too few to fit (an all-black or saturated frame): drawn from all, so that
                # the fit's reason names the clipped and dark pixels, not "no depth"
                enough = np.count_nonzero(candidates) >= self.config.estimation.min_samples
                vs, us = random_pixels(candidates if enough else has_geometry, budget, seed)
                t, b, ok = at_pixels(us, vs)
                return TransferSamples(
                    vs[ok],
                    us[ok],
                    t[ok].astype(np.float32),
                    None if lum is None else b[ok, 0].astype(np.float32),
                    clipped if enough else None,
                )
            grid = compute_transfer(
                geometry.points,
                geometry.normals,
                self.work_camera,
                pose,
                self.pattern,
                aux,
                p,
                lum,
                plane,
            )
        interpolate_to = has_geometry if p.rt_upsample and p.rt_subsample > 1 else None
        samples, (vs, us) = interpolated_samples(
            grid, interpolate_to, budget, seed, p.rt_refine_spread
        )
        if not len(vs) or p.rt_method is RtMethod.RAYCAST:
            return samples
        t, b, ok = at_pixels(us, vs)  # edges: their own transfer, not the grid's
        return TransferSamples(
            np.concatenate([samples.pixel_v, vs[ok]]),
            np.concatenate([samples.pixel_u, us[ok]]),
            np.concatenate([samples.transfer, t[ok].astype(np.float32)]),
            None if lum is None else np.concatenate([samples.bounce, b[ok, 0].astype(np.float32)]),
        )

    def _segments(self, color_linear: np.ndarray, geometry: _Geometry) -> np.ndarray | None:
        """(H, W) material labels for the light estimate (albedo_segments), or None."""
        p = self.config.estimation
        if not p.albedo_segments:
            return None
        # the scale, the threshold and the smallest segment are given in input pixels: a
        # reduced work image draws the segments a full-size one would (before, `fast`'s were
        # 4x larger: docs/decisions/0058-segments-in-input-pixels.md)
        area = self.work_scale**2
        segments = material_segments(
            color_linear,
            geometry.depth_m,
            scale=max(1, p.segment_scale // self.work_scale),
            k=SEGMENT_K * p.segment_coarseness / area,
            min_size_px=max(1, round(SEGMENT_MIN_SIZE_PX * p.segment_coarseness / area)),
            features=p.segment_features.value,
            illuminant_weight=p.segment_illuminant_weight,
        )
        if geometry.plane is not None and p.segment_split_ground:
            # what stands on the ground is rarely made of the ground's material
            segments = segments * 2 + geometry.plane.on_plane
        return segments
