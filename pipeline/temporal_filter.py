"""The temporal filter of the light estimate: world-frame SH smoothed over frames,
restarted when the light really changes."""

from __future__ import annotations

import math

import numpy as np

from arlight.pipeline import sh
from arlight.pipeline.config import TemporalParams


class TemporalFilter:
    """Exponential smoothing of world-frame SH that still follows a real light change.

    Each frame blends in the new estimate with weight 1 - 0.5^(1 / half_life) (scaled by
    its confidence); when the dominant direction jumps by more than `change_reset_rad` for
    two frames in a row, the filter restarts from the new light (a switched lamp). Half-life
    0: off, each frame's own estimate (a frame without one keeps the last).
    """

    def __init__(self, params: TemporalParams) -> None:
        # half-life 0: no smoothing, each frame's own estimate (a tiny half-life still
        # blends a frame of confidence below 0.5 with the last: its weight is scaled down)
        self.off = params.temporal_half_life_frames == 0.0
        self.alpha = 1.0 - 0.5 ** (1.0 / max(params.temporal_half_life_frames, 1e-6))
        self.reset_cos = math.cos(params.change_reset_rad)
        self.state: np.ndarray | None = None
        self.pending_jump = 0

    def update(self, coeffs: np.ndarray, confidence: float) -> np.ndarray:
        c = np.asarray(coeffs, dtype=np.float64)
        if confidence <= 0.0:
            return self.state.copy() if self.state is not None else c
        if self.state is None or self.off:
            self.state = c.copy()
            return self.state.copy()
        d_new, d_old = sh.dominant_direction(c), sh.dominant_direction(self.state)
        if np.any(d_new) and np.any(d_old) and float(d_new @ d_old) < self.reset_cos:
            self.pending_jump += 1
            if self.pending_jump >= 2:
                self.state = c.copy()
                self.pending_jump = 0
                return self.state.copy()
        else:
            self.pending_jump = 0
        a = self.alpha * min(1.0, max(confidence, 0.2) / 0.5)
        self.state = (1.0 - a) * self.state + a * c
        return self.state.copy()
