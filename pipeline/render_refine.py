"""Where a sub-sampled differential render takes a second, finer grid (issue 32).

With render_subsample s > 1 the shading change that the virtual objects bring to real
pixels (the ratio R'_d / R_d and the indirect delta) is computed on an s x s grid and
up-sampled (`rendering`). A shadow's edge is then as soft as the grid is coarse. With
`render_refine` = t > 0, the coarse cells where the change varies enough for interpolation
to miss it (a ratio t or more from a neighbour's) are computed again on a grid of s / 2; the
rest of the rect keeps the coarse result, sampled at the fine grid's points, and the fine
grid is up-sampled as the coarse one was, its blur scaled with the step.

Grids are in pixels of the composite: the coarse grid's point of cell (i, j) is
(u0 + j s + s // 2, v0 + i s + s // 2), clipped to the rect; the fine grid's of cell (a, b)
(u0 + b f + f // 2, v0 + a f + f // 2), f = s // 2, so that fine cell (a, b) starts in
coarse cell (a f // s, b f // s).
"""

from __future__ import annotations

import numpy as np


def grid_points(start: int, stop: int, step: int) -> np.ndarray:
    """The grid's pixel coordinates along one axis of the rect [start, stop)."""
    return np.minimum(np.arange(start, stop, step) + step // 2, stop - 1)


def cells_to_refine(ratio: np.ndarray, valid: np.ndarray, threshold: float) -> np.ndarray:
    """(gh, gw) bool: valid coarse cells whose ratio differs from a valid neighbour's (of 8)
    by `threshold` or more, where interpolating between the two can be far off: a shadow's
    edge, not its smooth inside or the far, faint occlusion."""
    padded = np.pad(np.where(valid, ratio, np.nan), 1, constant_values=np.nan)
    h, w = ratio.shape
    spread = np.zeros((h, w))
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            if dv or du:
                other = padded[1 + dv : 1 + dv + h, 1 + du : 1 + du + w]
                spread = np.fmax(spread, np.abs(other - ratio))
    return valid & (spread >= threshold)


def fine_of_coarse(
    refine: np.ndarray, fine_shape: tuple[int, int], fine_step: int, step: int
) -> np.ndarray:
    """(fh, fw) bool: the fine cells (fine_step pixels) that start in refined coarse cells
    (step pixels)."""
    rows = np.minimum(np.arange(fine_shape[0]) * fine_step // step, refine.shape[0] - 1)
    cols = np.minimum(np.arange(fine_shape[1]) * fine_step // step, refine.shape[1] - 1)
    return refine[np.ix_(rows, cols)]


__all__ = ["cells_to_refine", "fine_of_coarse", "grid_points"]
