"""Per-frame input and output of the pipeline (docs/architecture.md, "Data flow")."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FrameInput:
    """One RGB-D frame.

    color: (H, W, 3) uint8, RGB order, sRGB-encoded.
    depth: (H, W) along the optical axis, 0 = missing: the sensor's uint16 units with
        `depth_scale` units per metre (what sources yield), or float metres (NaN = missing)
        with depth_scale None. `Pipeline.process` converts to metres, once.
    timestamp: seconds (sender clock).
    pose: optional (4, 4) camera-to-world (world_from_cam); when given, tracking is skipped.
    panorama: optional equirectangular LDR uint8 image for the 360-degree path.
    """

    color: np.ndarray
    depth: np.ndarray
    timestamp: float = 0.0
    pose: np.ndarray | None = None
    panorama: np.ndarray | None = None
    depth_scale: float | None = None


@dataclass
class Confidence:
    """What the data could constrain in one light estimate.

    samples: pixels used in the least-squares fit; condition_number: of the (unregularised,
    column-scaled) normal matrix; bands_estimated: SH bands solved for (the rest are zero);
    value: overall confidence in [0, 1] (0 = no estimate possible); reason: why the value is
    low (below light_estimation.LOW_CONFIDENCE, or 0), naming the cause ("" otherwise);
    normal_spread: 1 - |mean unit normal|^2 of the pixels fitted (0 = one plane);
    horizon_disagreement_deg: degrees between the whole-sphere direction and the one above
    the support plane's horizon (0 without a plane); side_share: share of the fitted
    pixels' normals facing sideways to the support plane (None: no plane seen yet);
    jump_deg: degrees between this frame's direction and the filtered one before it.
    light_estimation says how each counts (the last two: `with_view_and_steadiness`).
    """

    samples: int = 0
    condition_number: float = float("inf")
    bands_estimated: int = 0
    value: float = 0.0
    reason: str = ""
    normal_spread: float = 0.0
    horizon_disagreement_deg: float = 0.0
    side_share: float | None = None
    jump_deg: float = 0.0

    def to_dict(self) -> dict:
        cond = self.condition_number
        return {
            "samples": int(self.samples),
            # JSON has no infinity: a system that could not be set up reports null
            "condition_number": float(cond) if np.isfinite(cond) else None,
            "bands_estimated": int(self.bands_estimated),
            "value": float(self.value),
            "reason": self.reason,
            "normal_spread": float(self.normal_spread),
            "horizon_disagreement_deg": float(self.horizon_disagreement_deg),
            "side_share": None if self.side_share is None else float(self.side_share),
            "jump_deg": float(self.jump_deg),
        }


@dataclass
class FrameResult:
    """Lighting estimated from one frame.

    sh: (L*L,) radiance SH of the distant light, luminance, in the WORLD frame
        (arlight.pipeline.sh conventions: orthonormal, no Condon-Shortley phase).
    sh_camera: the same light in the camera frame of this frame.
    sh_rgb: optional (3, L*L) per linear RGB channel, world frame.
    dominant_direction_world / _camera: unit vectors towards the light (zeros if none).
    intensity: radiance of the dominant light lobe (arbitrary units, camera exposure).
    pose: (4, 4) camera-to-world used for this frame.
    """

    timestamp: float
    sh: np.ndarray
    sh_camera: np.ndarray
    dominant_direction_world: np.ndarray
    dominant_direction_camera: np.ndarray
    intensity: float
    confidence: Confidence
    pose: np.ndarray
    sh_rgb: np.ndarray | None = None
    composite: np.ndarray | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
