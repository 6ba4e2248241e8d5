"""The typed contracts of the frame path: what the pipeline reports about one frame, read the
same way by the pipeline, the server, the protocol and the clients.

- `Confidence`: what the data could constrain in one light estimate. The pipeline makes it
  (FrameResult.confidence), the server sends it (Result.confidence: the map `to_dict` gives,
  SPEC.md section 4) and a client decodes it back into this class.
- `Diagnostics`: the keys of FrameResult.diagnostics and Result.diagnostics. Telemetry: a map
  of plain values that travels as it is; no control flow reads it (the pipeline's decisions
  read typed values, and record them here).

The lowest layer beside `arlight.core.checks`: the standard library only, so that every package
(pipeline, protocols, server, client) may depend down on it (tests/test_architecture.py).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, TypedDict


@dataclass
class Confidence:
    """What the data could constrain in one light estimate.

    samples: pixels used in the least-squares fit; condition_number: of the (unregularised,
    column-scaled) normal matrix; bands_estimated: SH bands solved for (the rest are zero);
    value: overall confidence in [0, 1] (0 = no estimate possible); reason: why the value is
    low (below light_confidence.LOW_CONFIDENCE, or 0), naming the cause ("" otherwise);
    normal_spread: 1 - |mean unit normal|^2 of the pixels fitted (0 = one plane);
    horizon_disagreement_deg: degrees between the whole-sphere direction and the one above
    the support plane's horizon (0 without a plane); side_share: share of the fitted
    pixels' normals facing sideways to the support plane (None: no plane seen yet);
    jump_deg: degrees between this frame's direction and the filtered one before it.
    light_confidence says how each counts (the last two: `with_view_and_steadiness`).
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

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON values, in this key order: Result.confidence on the wire."""
        cond = float(self.condition_number)
        return {
            "samples": int(self.samples),
            # JSON has no infinity: a system that could not be set up reports null
            "condition_number": cond if math.isfinite(cond) else None,
            "bands_estimated": int(self.bands_estimated),
            "value": float(self.value),
            "reason": self.reason,
            "normal_spread": float(self.normal_spread),
            "horizon_disagreement_deg": float(self.horizon_disagreement_deg),
            "side_share": None if self.side_share is None else float(self.side_share),
            "jump_deg": float(self.jump_deg),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Confidence:
        """The inverse of `to_dict`, for a map from the wire or a JSON record.

        Each field is read from its key when the value has the field's type (an int where a
        float is expected counts; null condition_number is infinite, as `to_dict` writes
        it); a missing or mistyped key leaves the field's default, and keys of no field are
        not read (the protocol carries any plain map: SPEC.md, "result")."""
        out = cls()
        for f in fields(cls):
            if f.name not in d:
                continue
            value = d[f.name]
            kind = _FIELD_KINDS[f.name]
            if value is None and f.name == "condition_number":
                out.condition_number = math.inf
            elif value is None and f.name == "side_share":
                out.side_share = None
            elif kind is int and type(value) is int:
                setattr(out, f.name, value)
            elif kind is float and type(value) in (int, float):
                setattr(out, f.name, float(value))
            elif kind is str and type(value) is str:
                setattr(out, f.name, value)
        return out


_FIELD_KINDS: dict[str, type] = {
    "samples": int,
    "condition_number": float,
    "bands_estimated": int,
    "value": float,
    "reason": str,
    "normal_spread": float,
    "horizon_disagreement_deg": float,
    "side_share": float,
    "jump_deg": float,
}


class TrackingDiagnostics(TypedDict, total=False):
    """Diagnostics["tracking"]: ok, and why not ("" when ok); inlier_fraction: ICP inliers per
    valid input depth pixel (absent where ICP did not run)."""

    ok: bool
    reason: str
    inlier_fraction: float


class ReusedStages(TypedDict):
    """Diagnostics["reused"]: per stage, whether a still camera's earlier output served."""

    Surface: bool
    DynGeo: bool
    RadTransfer: bool


class CompactDiagnostics(TypedDict):
    """Diagnostics["compact"]: why a source was kept (or none), the visibility rays cast to
    find them, how many were kept (at most compact_sources) and each one's gain (the share
    of the SH fit's residual its shadow explains), the step (ln luminance) the image shows
    across the best direction's shadow edge, kept or not, and whether the frame searched every
    candidate direction (else it refined the last frame's: compact_search_interval); the
    sources themselves are FrameResult.compact_sources (the Result's `compact_sources`)."""

    reason: str
    rays: int
    kept: int
    gain: list[float]
    edge_step: float
    searched: bool


class Diagnostics(TypedDict, total=False):
    """What the pipeline and the server report about one frame besides the estimate.

    Every key is optional (a panorama-only frame has only the last two); a client must not
    fail on keys it does not know (SPEC.md, "diagnostics"). Directions are unit vectors, or zeros
    where there is none.
    """

    tracking_ok: bool  # the frame was tracked (or its pose given): a record, not a switch
    tracking: TrackingDiagnostics
    reused: ReusedStages
    residual_rel: float | None  # relative residual of the light fit (None: not finite)
    bounce_scale: float
    horizon_prior_used: bool
    support_plane_up_world: list[float] | None
    raw_dominant_direction_world: list[float]  # before the temporal filter
    sh_direction_world: list[float]  # the filtered SH's own, a source kept or not (LightOutcome)
    bands_requested: int
    bands_estimated: int
    confidence_reason: str  # Confidence.reason as reported
    fit_disagreement_deg: float  # between the fits near the look-at point and of the whole view
    compact: CompactDiagnostics  # compact sources beside the SH (compact_sources > 0)
    light_source: str  # the server, a session with a panorama: "rgbd" or "panorama"
    panorama_operator: str  # the server: the inverse tone mapping operator used
    probe: dict[str, Any]  # the reflection probe's notes (pipeline/probe.py), when one is made
