"""Per-frame input and output of the pipeline (docs/architecture.md, "Data flow").

Confidence and Diagnostics are the frame path's shared contracts (arlight.core.contracts: the
protocol and the clients read the same types); they are re-exported here."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np

from arlight.core.contracts import Confidence, Diagnostics

__all__ = [
    "CompactLight",
    "Confidence",
    "Diagnostics",
    "FrameInput",
    "FrameResult",
    "RenderLight",
    "compact_lights",
]


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


@dataclass(frozen=True)
class CompactLight:
    """A compact distant light (a sun, a lamp) found beside the SH in one frame.

    direction_world / direction_camera: (3,) unit vectors towards the source (world frame;
    camera frame = R^T world with R the pose's rotation). intensity: its luminance integrated
    over its solid angle (the irradiance on a surface facing it; the units of FrameResult.sh,
    whose projection of it is intensity * Y(direction_world)). rgb: (3,) the same per linear
    R, G, B (each >= 0), or None. angular_radius_deg: degrees, assumed (not measured).
    share: 0..1, the source's part of the irradiance on a surface facing it.
    """

    direction_world: np.ndarray
    direction_camera: np.ndarray
    intensity: float
    rgb: np.ndarray | None
    angular_radius_deg: float
    share: float


class _FittedSource(Protocol):
    """What compact_lights reads of a pipeline.compact_light.CompactSource."""

    @property
    def direction(self) -> np.ndarray: ...
    @property
    def intensity(self) -> float: ...
    @property
    def rgb(self) -> np.ndarray | None: ...
    @property
    def angular_radius_deg(self) -> float: ...
    @property
    def share(self) -> float: ...


def compact_lights(
    sources: Sequence[_FittedSource], world_from_cam_rotation: np.ndarray
) -> tuple[CompactLight, ...]:
    """The frame's fitted compact sources (world frame) as CompactLights, in the camera frame
    too: direction_camera = R^T direction_world, R (3, 3) camera-to-world rotation. A
    channel of rgb fitted below 0 is reported as 0 (its light cannot be negative)."""
    r = np.asarray(world_from_cam_rotation, dtype=np.float64)
    out = []
    for s in sources:
        d = np.asarray(s.direction, dtype=np.float64).copy()
        rgb = None if s.rgb is None else np.maximum(np.asarray(s.rgb, np.float64), 0.0)
        out.append(
            CompactLight(
                direction_world=d,
                direction_camera=r.T @ d,
                intensity=max(float(s.intensity), 0.0),
                rgb=rgb,
                angular_radius_deg=float(s.angular_radius_deg),
                share=float(s.share),
            )
        )
    return tuple(out)


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
    compact_sources: the compact sources kept beside the SH this frame (at most 4; the
        first is the one the dominant direction names); () when none. `sh` still holds the
        whole light: the sources say where its compact part is.
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
    compact_sources: tuple[CompactLight, ...] = ()
