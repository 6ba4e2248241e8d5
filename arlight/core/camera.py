"""Pinhole camera model in OpenCV axes (x right, y down, z forward), pixel centres at integers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of an undistorted pinhole camera.

    width, height: image size in pixels; fx, fy: focal lengths in pixels;
    cx, cy: principal point in pixels (the centre of pixel (u, v) is at (u, v)).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera size must be >= 1x1 pixels, got {self.width}x{self.height}")
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"camera {name} must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0 pixels, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def kinect_v1(cls, width: int = 640, height: int = 480) -> PinholeCamera:
        """Kinect v1 default intrinsics (fx = fy = 525, centre at the image middle), scaled."""
        s = width / 640.0
        return cls(width, height, 525.0 * s, 525.0 * s, (width - 1) / 2.0, (height - 1) / 2.0)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, width: int, height: int) -> PinholeCamera:
        k = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
        return cls(
            int(width), int(height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
        )

    @property
    def matrix(self) -> np.ndarray:
        """3x3 intrinsic matrix K (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> PinholeCamera:
        """The same camera for an image resized by `factor` (pixel centres kept consistent)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        return PinholeCamera(
            w,
            h,
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
        )

    def reduced(self, scale: int) -> PinholeCamera:
        """The camera whose pixel (i, j) covers pixels scale i .. scale i + scale - 1 (rows)
        and scale j .. (columns) of this one (sizes rounded up; `self` when scale is 1)."""
        if scale == 1:
            return self
        return PinholeCamera(
            -(-self.width // scale),
            -(-self.height // scale),
            self.fx / scale,
            self.fy / scale,
            (self.cx + 0.5) / scale - 0.5,
            (self.cy + 0.5) / scale - 0.5,
        )

    def unproject(self, depth_m: np.ndarray) -> np.ndarray:
        """Camera-frame points (H, W, 3) float32, metres, from depth (H, W) metres (z along axis).

        Missing depth (0 or NaN) gives points with z = 0 or NaN; callers mask them.
        """
        h, w = depth_m.shape
        u = (np.arange(w, dtype=np.float32) - np.float32(self.cx)) / np.float32(self.fx)
        v = (np.arange(h, dtype=np.float32) - np.float32(self.cy)) / np.float32(self.fy)
        z = depth_m.astype(np.float32, copy=False)
        out = np.empty((h, w, 3), np.float32)  # (each channel written in place: no stack)
        np.multiply(z, u[None, :], out=out[..., 0])
        np.multiply(z, v[:, None], out=out[..., 1])
        out[..., 2] = z
        return out

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) as (u, v) and depth z (...,) of camera points (..., 3)."""
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * p[..., 0] / z + self.cx
            v = self.fy * p[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1), z

    def ray_directions(self) -> np.ndarray:
        """Unit viewing rays (H, W, 3) float32 in the camera frame, through every pixel centre."""
        rays = self.unproject(np.ones((self.height, self.width), np.float32))
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)
