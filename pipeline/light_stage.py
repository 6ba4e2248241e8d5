"""LightEst as a session keeps it: the SH fits, their blend, the compact sources, the
temporal filter, and what a frame reports (direction, intensity, confidence, diagnostics).

`LightStage.run` takes one frame's sampled transfer (RadTransfer's output) and returns a
`LightOutcome`. The stage holds what carries over between frames: the temporal filter, the
support plane's "up" last seen, the reported direction last frame (the steadiness factor,
the auxiliary "light" buffer), and the compact sources' search. Frames are world frame
unless named otherwise; the fit itself is `light_estimation.estimate_light` (section 5.2).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from arlight.core.frames import Confidence, Diagnostics
from arlight.pipeline import sh
from arlight.pipeline.compact_light import CompactFit, CompactSource, source_confidence
from arlight.pipeline.compact_stage import CompactLightStage
from arlight.pipeline.config import Config
from arlight.pipeline.fit_region import blended, near_look_at, whole_view_share
from arlight.pipeline.light_confidence import side_share, with_view_and_steadiness
from arlight.pipeline.light_estimation import LightEstimate, estimate_light
from arlight.pipeline.object_space_transfer import ObjectSpaceTransfer, OcclusionScene
from arlight.pipeline.radiance_transfer import TransferSamples
from arlight.pipeline.temporal_filter import TemporalFilter

# the compact sources' occluder without the volume's mesh: the frame's depth mesh about this
# many points wide, 160x120 of 640x480 (docs/decisions/0060-compact-depth-mesh.md)
COMPACT_DEPTH_MESH_WIDTH = 160


@dataclass(frozen=True)
class LightFrame:
    """What LightEst reads of one frame (camera frame, work resolution).

    transfer: the sampled transfer; points, normals: (h, w, 3) of the surface; up_world:
    the support plane's normal this frame (world; None where no plane was found);
    color_linear: (h, w, 3); labels: (h, w) material segments or None; pose: (4, 4) world
    from camera; occluder: the reconstruction the compact sources' shadows are tested
    against (None without compact sources).
    """

    transfer: TransferSamples
    points: np.ndarray
    normals: np.ndarray
    up_world: np.ndarray | None
    color_linear: np.ndarray
    labels: np.ndarray | None
    pose: np.ndarray
    occluder: OcclusionScene | None = None


@dataclass(frozen=True)
class LightOutcome:
    """One frame's light as reported.

    estimate: the fit reported (blended with the whole view's where decision 0067 does);
    coeffs: (bands^2,) world luminance SH after the temporal filter; direction_world: unit,
    towards the light (the kept compact source's, else the filtered SH's above the
    horizon; zeros when there is none); intensity: of the delta light along it that best
    fits `coeffs`; confidence: as reported; raw_direction: before the filter (world);
    disagreement_deg: between the fits near the look-at point and over the whole view;
    sh_direction_world: the filtered SH's own direction, which a kept source's replaces as
    `direction_world` (above the support plane's horizon once one has been seen, else of
    the whole sphere; zeros when there is none); up_world: this frame's support plane's
    normal (world; None where none was found).
    """

    estimate: LightEstimate
    coeffs: np.ndarray
    direction_world: np.ndarray
    intensity: float
    confidence: Confidence
    raw_direction: np.ndarray
    disagreement_deg: float
    sh_direction_world: np.ndarray
    up_world: np.ndarray | None


class LightStage:
    """One session's LightEst (see the module docstring). Not thread-safe.

    work_width: pixels of the analysed frame (the compact sources' depth mesh is cut from
    it); raycaster: the session's ray-casting scene under rt_method raycast, else None.
    """

    def __init__(
        self, config: Config, work_width: int, raycaster: ObjectSpaceTransfer | None = None
    ):
        self.config = config
        self.work_width = work_width
        self.raycaster = raycaster
        self.filter = TemporalFilter(config.temporal)
        self.up_world: np.ndarray | None = None  # of the support plane, last seen
        self.light_world: np.ndarray | None = None  # the direction reported last
        self.compact_stage: CompactLightStage | None = None  # made on first use
        self.last_compact: CompactFit | None = None

    def compact(self) -> CompactLightStage:
        """The session's compact-source stage (made on first use): against the frame's depth
        mesh, or with compact_volume_mesh the volume's (with rt_method raycast, the
        transfer's scene of it)."""
        if self.compact_stage is None:
            p = self.config.estimation
            self.compact_stage = CompactLightStage(
                self.config.aux.aux_update_interval,
                self.raycaster,
                p.compact_search_interval,
                None
                if p.compact_volume_mesh
                else max(1, round(self.work_width / COMPACT_DEPTH_MESH_WIDTH)),
            )
        return self.compact_stage

    def run(
        self, frame: LightFrame, check: Callable[[str], None], diagnostics: Diagnostics
    ) -> LightOutcome:
        """The frame's fits, compact sources, blend, filter and report; with compact
        sources, what the search found and why to diagnostics["compact"]. check: called
        with "LightEst" before each pass of the fit (whatever it raises abandons the
        frame)."""
        up_world = frame.up_world
        near, estimate, searched, search_estimate = self.fits(frame, check)
        self.last_compact = self._compact_sources(search_estimate, frame, searched, diagnostics)
        if up_world is not None:
            self.up_world = up_world
        disagreement = self.disagreement_deg(estimate, search_estimate)
        p = self.config.estimation
        if disagreement < p.fit_radius_agree_deg:
            estimate = search_estimate
        elif search_estimate is not estimate:
            share = whole_view_share(disagreement, p.fit_radius_blend, p.fit_radius_blend_deg)
            if share > 0.0:
                estimate = blended(estimate, search_estimate, share)
        coeffs = self.filter.update(estimate.sh, estimate.confidence.value)
        source = self.kept_source()
        raw_direction = self.light_direction(estimate.sh) if source is None else source.direction
        confidence = self._reported_confidence(
            estimate, raw_direction, near, frame, source is not None, disagreement
        )
        sh_direction = self.light_direction(coeffs)
        direction_world = sh_direction.copy() if source is None else source.direction.copy()
        intensity = sh.intensity_along(coeffs, direction_world)
        if np.any(direction_world):
            self.light_world = direction_world
        return LightOutcome(
            estimate,
            coeffs,
            direction_world,
            intensity,
            confidence,
            raw_direction,
            disagreement,
            sh_direction,
            up_world,
        )

    def fits(
        self, frame: LightFrame, check: Callable[[str], None]
    ) -> tuple[TransferSamples, LightEstimate, TransferSamples, LightEstimate]:
        """The SH fits: to the samples near the look-at point (fit_radius_m; every one when
        0) and, with fit_radius_sources_everywhere, to every sample for the compact sources'
        search (at most fit_radius_sources_samples; decision 0064). Returns (the near
        samples, their estimate, the samples searched, their estimate): one fit twice when
        there is no second."""
        p = self.config.estimation
        transfer = frame.transfer
        near = near_look_at(transfer, frame.points, p.fit_radius_m)

        def fitted(samples: TransferSamples, max_samples: int = 0) -> LightEstimate:
            return self.estimate(
                samples,
                frame.color_linear,
                frame.labels,
                frame.up_world,
                below_horizon_unseen=self.config.transfer.rt_horizon,
                checkpoint=lambda: check("LightEst"),
                max_samples=max_samples,
            )

        estimate = fitted(near)
        if p.fit_radius_sources_everywhere and p.compact_sources > 0 and near is not transfer:
            return near, estimate, transfer, fitted(transfer, p.fit_radius_sources_samples)
        return near, estimate, near, estimate

    def estimate(
        self,
        samples: TransferSamples,
        color_linear: np.ndarray,
        segments: np.ndarray | None,
        up_world: np.ndarray | None = None,
        below_horizon_unseen: bool = False,
        checkpoint: Callable[[], None] | None = None,
        max_samples: int = 0,
    ) -> LightEstimate:
        """LightEst (T l = I_c, section 5.2) on the sampled pixels; albedo per segment
        (segments: (h, w) labels or None); at most max_samples of them (0: the config's
        light_max_samples)."""
        p = self.config.estimation
        if max_samples > 0:
            p = dataclasses.replace(p, light_max_samples=max_samples)
        n = samples.transfer.shape[-1]
        if not len(samples.pixel_v):
            return LightEstimate(
                np.zeros(n),
                Confidence(reason="no valid depth"),
                np.zeros((3, n)) if p.estimate_rgb else None,
            )
        pixels = (samples.pixel_v, samples.pixel_u)
        return estimate_light(
            samples.transfer,
            color_linear[pixels],
            p,
            None if segments is None else segments[pixels],
            samples.bounce,
            up_world,
            below_horizon_unseen,
            seed=self.config.seed,
            checkpoint=checkpoint,
            clipped_fraction=samples.clipped_fraction,
        )

    def disagreement_deg(self, near: LightEstimate, whole: LightEstimate) -> float:
        """Degrees between the reported directions of the fit near the look-at point and the
        whole view's (0 when they are one fit, or either has no first band)."""
        if whole is near or not all(np.any(e.sh[1:4]) for e in (near, whole)):
            return 0.0
        cos = float(self.light_direction(whole.sh) @ self.light_direction(near.sh))
        return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))

    def light_direction(self, coeffs: np.ndarray) -> np.ndarray:
        """The dominant direction reported (world): of the light above the horizon of the
        surface the scene stands on, once one has been seen (the estimate's glow from below
        taken out, sh.above_horizon_direction), else of the whole sphere."""
        if self.up_world is None:
            return sh.dominant_direction(coeffs)
        return sh.above_horizon_direction(coeffs, self.up_world)

    def kept_source(self) -> CompactSource | None:
        """This frame's compact source, when one was kept: the direction reported is then
        its direction (the shadows the scene casts point there), not the SH's first
        moment (far closer under a sun, not yet under soft light: opt-in,
        docs/decisions/0035-compact-sources.md)."""
        fit = self.last_compact
        return fit.sources[0] if fit is not None and fit.sources else None

    def _compact_sources(
        self,
        estimate: LightEstimate,
        frame: LightFrame,
        transfer: TransferSamples,
        diagnostics: Diagnostics,
    ) -> CompactFit | None:
        """Compact sources beside the SH (compact_sources > 0): found from the shadows the
        reconstruction (`frame.occluder`) casts (pipeline/compact_light.py); what was
        found, and why, to diagnostics["compact"]."""
        p = self.config.estimation
        if p.compact_sources <= 0 or estimate.fit is None or frame.occluder is None:
            return None
        fit, rays = self.compact().fit_against(
            frame.occluder,
            estimate.fit,
            frame.points,
            frame.normals,
            transfer.pixel_v,
            transfer.pixel_u,
            frame.pose,
            frame.up_world if frame.up_world is not None else self.up_world,
            {
                "candidates": p.compact_candidates,
                "search_samples": p.compact_search_samples,
                "min_gain": p.compact_min_gain,
                "min_contrast": p.compact_min_contrast,
                "min_edge_step": p.compact_min_edge_step,
                "min_elevation_deg": p.compact_min_elevation_deg,
                "max_sources": p.compact_sources,
            },
            seed=self.config.seed,
            with_depth=p.compact_depth_mesh,
        )
        diagnostics["compact"] = {
            "reason": fit.reason,
            "rays": int(rays),
            # the sources themselves: FrameResult.compact_sources (diagnostics carry no
            # arrays of maps on the wire, SPEC.md "diagnostics")
            "kept": len(fit.sources),
            "gain": [float(s.gain) for s in fit.sources],
            "edge_step": float(fit.edge_step),
            "searched": self.compact().last_searched,
        }
        return fit

    def _reported_confidence(
        self,
        estimate: LightEstimate,
        raw: np.ndarray,
        transfer: TransferSamples,
        frame: LightFrame,
        from_source: bool = False,
        disagreement_deg: float = 0.0,
    ) -> Confidence:
        """The estimate's confidence times what one fit cannot know of itself
        (`light_confidence.with_view_and_steadiness`): the share of side-facing normals
        among the fitted pixels (against this frame's support plane, or the last one seen)
        and the jump of this frame's direction `raw` (world, before the filter) from the
        filtered one before it (called before `light_world` takes this frame's).
        from_source: `raw` is a kept compact source's direction, found from shadows, not
        from the normals: its confidence is how clear the step across its shadow's edge is
        (`compact_light.source_confidence`), and the view of side-facing normals does not
        count. disagreement_deg: between the SH fits near the look-at point and over the
        whole view (0 with one fit)."""
        jump = 0.0
        if self.light_world is not None and np.any(raw):
            jump = math.degrees(math.acos(float(np.clip(raw @ self.light_world, -1.0, 1.0))))
        if from_source and self.last_compact is not None:
            base = source_confidence(estimate.confidence, self.last_compact.edge_step)
            return with_view_and_steadiness(base, None, jump)
        normals = frame.normals[transfer.pixel_v, transfer.pixel_u].astype(np.float64)
        side = side_share(normals @ frame.pose[:3, :3].T, self.up_world)
        return with_view_and_steadiness(estimate.confidence, side, jump, disagreement_deg)

    def diagnostics_of(self, outcome: LightOutcome) -> Diagnostics:
        """Plain JSON types (the wire carries them): what the light estimate did and why
        (LightOutcome's fields; fit_disagreement_deg is the confidence's "agreement"
        factor's angle, 0 with one fit)."""
        estimate = outcome.estimate
        residual = estimate.residual_rel
        return {
            "residual_rel": float(residual) if math.isfinite(residual) else None,
            "bounce_scale": float(estimate.bounce_scale),
            "horizon_prior_used": bool(estimate.horizon_prior_used),
            "support_plane_up_world": (
                None if outcome.up_world is None else [float(x) for x in outcome.up_world]
            ),
            "raw_dominant_direction_world": [float(x) for x in outcome.raw_direction],
            "sh_direction_world": [float(x) for x in outcome.sh_direction_world],
            "bands_requested": int(self.config.transfer.sh_bands),
            "bands_estimated": int(estimate.confidence.bands_estimated),
            "confidence_reason": outcome.confidence.reason,  # the reported one
            "fit_disagreement_deg": float(outcome.disagreement_deg),
        }
