"""Per-frame input and output of the pipeline (docs/architecture.md, "Data flow").

Confidence and Diagnostics are the frame path's shared contracts (arlight.core.contracts: the
protocol and the clients read the same types); they are re-exported here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from arlight.core.contracts import Confidence, Diagnostics

__all__ = ["Confidence", "Diagnostics", "FrameInput", "FrameResult", "RenderLight"]


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


class RenderLight(NamedTuple):
    """An outside light that renders the virtual objects instead of the frame's estimate (a
    session lit by its 360-degree panorama; `Pipeline.process(render_light=...)`).

    sh: (n,) radiance SH, WORLD frame, the light's own units (no albedo scaling); sh_rgb:
    (3, n) per linear RGB channel, or None; environment: a `rendering.EnvironmentMap` (the
    panorama's HDR map) that mirror and glossy objects reflect, or None. Typed `object` here:
    the lowest layer imports no pipeline module; `Pipeline.process` checks its type.
    """

    sh: np.ndarray
    sh_rgb: np.ndarray | None = None
    environment: object | None = None


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
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
