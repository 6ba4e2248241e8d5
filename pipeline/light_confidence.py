"""How far to trust one frame's light estimate: the confidence (0..1) and, when it is low,
the reason in words.

A fit's own evidence (FitEvidence: its samples, the conditioning of its normal matrix, the
bands it could estimate, how many ways the normals face, how much of the light falls below
the support plane's horizon) gives the factors multiplied into `Confidence.value`
(light_estimation.estimate_light); what one fit cannot know of itself (side-facing
normals, a jump from the last frames' estimate, two fits of one frame that disagree) is
multiplied in by the session (`with_view_and_steadiness`). Why these factors:
docs/results/confidence.md and the decision records it links.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from arlight.core.frames import Confidence
from arlight.pipeline.channels import vector_length


@dataclass(frozen=True)
class FitEvidence:
    """What one fit had to go on: the inputs of its confidence."""

    samples: int
    cond: float
    bands: int
    normal_spread: float  # light_estimation.normal_spread(), 0..1
    horizon_deg: float  # light_estimation.horizon_disagreement_deg(), degrees
    residual_rel: float  # reported, not a factor (see confidence_factors)
    clipped_fraction: float = 0.0  # named in the reason, not a factor (no data to rank it)


# spread at which the normals factor reaches 1: views near one plane only (0.3 ranked the error
# worse on held-out maps; docs/decisions/0066-confidence-view-normals-jump.md)
NORMAL_SPREAD_FULL = 0.1
# the conditioning factor (COND_GOOD / cond) ** COND_POWER, at most 1: fits have condition
# numbers of 1e3-1e5, over which 1 / (1 + log10(cond) / 5) fell only from 0.62 to 0.50;
# chosen leaving maps out (docs/decisions/0065-confidence-conditioning.md)
COND_GOOD = 1e3
COND_POWER = 0.8
HORIZON_SCALE_DEG = 40.0  # horizon factor exp(-disagreement / this)
SAMPLES_FULL = 5000  # fitted pixels at which the samples factor reaches 1
NO_DIRECTION_FACTOR = 0.3  # the bands factor without band 1 (no direction estimated)
MIN_FACTOR = 0.02  # a factor's floor: a weak estimate is still an estimate (value 0: none)


def confidence_factors(e: FitEvidence) -> dict[str, float]:
    """The factors of the confidence, each in [MIN_FACTOR, 1] (samples, bands: [0, 1]).

    Why these factors and not the fit's residual (which ranks textured scenes wrongly):
    docs/results/confidence.md and docs/decisions/0003-confidence-spread-and-horizon.md.
    """
    return {
        "samples": min(1.0, e.samples / SAMPLES_FULL),
        "conditioning": conditioning_factor(e.cond),
        "bands": 1.0 if e.bands >= 2 else NO_DIRECTION_FACTOR,
        "normals": max(MIN_FACTOR, min(1.0, e.normal_spread / NORMAL_SPREAD_FULL)),
        "horizon": max(MIN_FACTOR, math.exp(-e.horizon_deg / HORIZON_SCALE_DEG)),
    }


def conditioning_factor(condition_number: float) -> float:
    """The confidence's conditioning factor, (COND_GOOD / cond) ** COND_POWER in [MIN_FACTOR,
    1]: 1 at a condition number of 1e3 or less, 0.16 at 1e4, 0.025 at 1e5."""
    return max(MIN_FACTOR, min(1.0, (COND_GOOD / max(condition_number, 1.0)) ** COND_POWER))


def confidence_value(e: FitEvidence) -> float:
    """[0, 1]: enough samples, a well-posed system, normals facing many ways, light that
    lies where the scene can receive it. 0: no estimate."""
    if e.samples == 0 or not np.isfinite(e.cond):
        return 0.0
    return float(np.clip(math.prod(confidence_factors(e).values()), 0.0, 1.0))


LOW_CONFIDENCE = 0.3  # below this, Confidence.reason names the causes
WEAK_FACTOR = 0.6  # a confidence factor below this is named as a cause


def low_confidence_reason(e: FitEvidence, max_bands: int, value: float) -> str:
    """Why the confidence is low ("" when it is not): every weak factor, by name."""
    if value >= LOW_CONFIDENCE:
        return ""
    if e.samples == 0:
        return "no usable pixels"
    if not np.isfinite(e.cond):
        return "singular system: the normals constrain no light"
    text = {
        "samples": f"few usable pixels ({e.samples})",
        "conditioning": f"ill-conditioned normals (condition number {e.cond:.3g}, "
        f"{e.bands} of {max_bands} bands estimated)",
        "bands": f"only band 0 estimated ({max_bands} asked): no direction",
        "normals": f"few normal directions (spread {e.normal_spread:.2f}: a wall or floor "
        f"alone shows the light's strength, not where it comes from)",
        "horizon": f"much of the light fitted lies below the support plane's horizon "
        f"(the direction above it is {e.horizon_deg:.0f} deg from the whole "
        f"sphere's): ground glow or light the normals leave unconstrained",
    }
    f = confidence_factors(e)
    weak = [name for name, v in f.items() if v < WEAK_FACTOR] or [min(f, key=lambda k: f[k])]
    causes = [text[name] for name in weak]
    if e.clipped_fraction > CLIPPED_NOTE:
        causes.append(
            f"{100 * e.clipped_fraction:.0f} % of the pixels clipped (emitters, "
            "windows or highlights in view: left out, and the light they cast may "
            "be missing from the fit)"
        )
    return "; ".join(causes)


CLIPPED_NOTE = 0.05  # a clipped fraction above this is named in a low confidence's reason

# What one fit cannot know of itself, multiplied into the confidence the pipeline reports
# (not into the temporal filter's weights: the estimate is unchanged): side-facing normals
# constrain where the light stands, and a jump from the last frames' estimate is a light
# change or an unreliable frame (docs/decisions/0004-confidence-view-and-steadiness.md).
SIDE_COS = 0.7  # |n . up| below this: a side-facing normal (over ~45 degrees off vertical)
# share of side-facing normals at which the "view" factor reaches 1, and the "steadiness"
# factor's exp(-jump / JUMP_SCALE_DEG): chosen leaving maps out (decision 0066)
SIDE_SHARE_FULL = 0.05
JUMP_SCALE_DEG = 15.0
AGREE_SCALE_DEG = 20.0  # "agreement" factor exp(-disagreement / this)


def side_share(normals_world: np.ndarray, up_world: np.ndarray | None) -> float | None:
    """Share (0..1) of unit normals (K, 3) that face sideways (|n . up| < SIDE_COS) with
    respect to the support plane's up (world frame); None without an up or normals."""
    n = np.asarray(normals_world, np.float64).reshape(-1, 3)
    length = vector_length(n)
    n = n[length > 0.5]
    if up_world is None or not len(n):
        return None
    up = np.asarray(up_world, np.float64) / max(float(np.linalg.norm(up_world)), 1e-12)
    return float(np.mean(np.abs(n @ up) / vector_length(n) < SIDE_COS))


def with_view_and_steadiness(
    conf: Confidence, side: float | None, jump_deg: float, disagreement_deg: float = 0.0
) -> Confidence:
    """`conf` times the "view" factor (min(1, side / SIDE_SHARE_FULL); 1 when side is
    None) and the "steadiness" factor (exp(-jump_deg / JUMP_SCALE_DEG); jump_deg: degrees
    between this frame's direction and the filtered one before it, 0 on a first frame), each
    floored at MIN_FACTOR; a low value's reason names them when they are weak.
    disagreement_deg: degrees between the directions of two fits of the same frame (near
    the look-at point and over the whole view, fit_radius_sources_everywhere), counted as
    a jump is (the "agreement" factor, exp(-disagreement / AGREE_SCALE_DEG))."""
    if conf.value <= 0.0:
        return dataclasses.replace(conf, side_share=side, jump_deg=jump_deg)
    factors = {
        "view": 1.0 if side is None else max(MIN_FACTOR, min(1.0, side / SIDE_SHARE_FULL)),
        "steadiness": max(MIN_FACTOR, math.exp(-jump_deg / JUMP_SCALE_DEG)),
        "agreement": max(MIN_FACTOR, math.exp(-disagreement_deg / AGREE_SCALE_DEG)),
    }
    value = float(np.clip(conf.value * math.prod(factors.values()), 0.0, 1.0))
    reason = conf.reason
    if value < LOW_CONFIDENCE:
        text = {
            "view": f"few side-facing surfaces ({100 * (side or 0.0):.0f} % of the normals: "
            "a view of mostly ground or table shows little of where the light "
            "stands)",
            "steadiness": f"the estimate jumped {jump_deg:.0f} deg from the last frames' "
            "(the light changed, or this frame is unreliable)",
            "agreement": f"the light fitted near the look-at point is {disagreement_deg:.0f} "
            "deg from the one fitted over the whole view (the view is lit unevenly)",
        }
        weak = [name for name, v in factors.items() if v < WEAK_FACTOR]
        if not reason and not weak:
            weak = [min(factors, key=lambda k: factors[k])]
        reason = "; ".join([reason] * bool(reason) + [text[name] for name in weak])
    return dataclasses.replace(conf, value=value, reason=reason, side_share=side, jump_deg=jump_deg)
