"""What the radiance transfer takes and gives: the auxiliary buffers packed for the kernels,
the transfer on its grid, and the depth-test constants that the Numba kernels
(`radiance_transfer.py`) and their NumPy oracle (`transfer_oracle.py`) share."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class AuxBufferArrays:
    """Auxiliary orthographic buffers packed for the kernel.

    depth (B, R, R) float32 metres along each buffer's +z (0 = none); buffer_from_cam
    (B, 3, 4) rigid transforms; pixel_size (B,) metres per pixel.
    """

    depth: np.ndarray
    buffer_from_cam: np.ndarray
    pixel_size: np.ndarray

    @classmethod
    def empty(cls) -> AuxBufferArrays:
        return cls(np.zeros((0, 1, 1), np.float32), np.zeros((0, 3, 4)), np.zeros(0))

    @classmethod
    def from_buffers(cls, buffers, world_from_cam: np.ndarray) -> AuxBufferArrays:
        """From `OrthoBuffer`s (world_from_buffer, depth_m, pixel_size_m) of one size."""
        if not buffers:
            return cls.empty()
        depth = np.stack([b.depth_m for b in buffers]).astype(np.float32)
        b_from_c = np.stack(
            [(np.linalg.inv(b.world_from_buffer) @ world_from_cam)[:3] for b in buffers]
        )
        pix = np.array([b.pixel_size_m for b in buffers], dtype=np.float64)
        return cls(depth, b_from_c, pix)


@dataclass
class TransferResult:
    """Per-pixel SH transfer on the (sub-sampled) grid.

    transfer: (Hs, Ws, C) float32, world-frame SH; valid: (Hs, Ws) bool;
    pixel_u, pixel_v: (Ws,), (Hs,) full-resolution pixel coordinates of the grid;
    bounce: (Hs, Ws) float32 one-bounce light from the occluders (units of the luminance
    image given to compute_transfer, times steradians), or None.
    """

    transfer: np.ndarray
    valid: np.ndarray
    pixel_u: np.ndarray
    pixel_v: np.ndarray
    bounce: np.ndarray | None = None


# Depth-test bias: a sample counts as behind a surface only beyond this margin (metres,
# absolute + relative to depth), against sensor noise and quantisation.
BIAS_ABS_M = 0.01
BIAS_REL = 0.01
# points more than this below the support plane are not shadowed by it (metres)
HORIZON_BELOW_M = 0.05
