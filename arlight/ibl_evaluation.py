"""The truth of an HDR panorama and the metrics of the 360-degree lighting path against it.

`benchmarks/ibl_truth.py` and `tests/test_ibl.py` measure with these:

- `HdrTruth`: of a linear HDR equirectangular map, at full resolution (every pixel, exact
  solid angles): its luminance radiance SH, dominant direction (first moment, as
  ``sh.dominant_direction``) and the irradiance E(n) = integral L(w) max(0, n . w) dw of
  its luminance at a fixed set of normals (``sh.fibonacci_sphere``, near-uniform over the
  whole sphere) by brute force: the reference every diffuse map is compared with.
- `best_scale` and `relative_irradiance_error`: an LDR frame knows radiance only up to a
  global factor, so a recovered irradiance e is first scaled by the s that minimises
  sum_k (s e_k / E_k - 1)^2 (the relative errors in the least-squares sense), then the
  error is mean_k |s e_k - E_k| / E_k (0 = exact).
- `sh_error`: |s c - c_true| / |c_true| (relative L2 over the 16 luminance coefficients)
  with the same s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arlight.pipeline import equirect, sh
from arlight.pipeline.color import LUMA

REFERENCE_NORMALS = 2048  # one every ~4.5 degrees
_CHUNK_PIXELS = 16384  # of the brute-force reference: (normals x chunk) float32 at a time


def irradiance_at(radiance: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (K,) float64 of an (H, W) equirectangular radiance map at unit `normals`
    (K, 3), by brute force over every pixel: sum_k L_k max(0, n . w_k) d_omega_k."""
    image = equirect.check_equirect(radiance, "radiance")
    if image.ndim != 2:
        raise ValueError(f"radiance: expected an (H, W) map, got shape {image.shape}")
    h, w = image.shape
    dirs = equirect.pixel_directions(h, w).reshape(-1, 3).astype(np.float32)
    weighted = (image * equirect.row_solid_angles(h, w)[:, None]).reshape(-1).astype(np.float32)
    n = np.asarray(normals, dtype=np.float32)
    out = np.zeros(n.shape[0], dtype=np.float64)
    for start in range(0, dirs.shape[0], _CHUNK_PIXELS):
        cos = n @ dirs[start : start + _CHUNK_PIXELS].T
        np.maximum(cos, 0.0, out=cos)
        out += cos @ weighted[start : start + _CHUNK_PIXELS]
    return out


@dataclass
class HdrTruth:
    """The lighting of one HDR map (panorama frame), from every pixel."""

    sh: np.ndarray  # (16,) luminance radiance SH, the project's convention
    dominant_direction: np.ndarray  # (3,) first moment, unit
    normals: np.ndarray  # (K, 3) where the irradiance is known
    irradiance: np.ndarray  # (K,) luminance irradiance at the normals

    def rotated_about_y(self, shift_columns: int, width: int) -> HdrTruth:
        """The truth of the map turned by np.roll(columns, -shift_columns) (a rotation by
        2 pi shift / width about +y, `equirect.rotate_about_y`): direction and normals turn
        with it, the irradiance values stay; SH rotated."""
        angle = 2.0 * np.pi * shift_columns / width
        c, s = np.cos(angle), np.sin(angle)
        r = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # R_y(angle)
        return HdrTruth(
            sh.rotate(self.sh, r), r @ self.dominant_direction, self.normals @ r.T, self.irradiance
        )


def hdr_truth(hdr_rgb: np.ndarray, num_normals: int = REFERENCE_NORMALS) -> HdrTruth:
    """`HdrTruth` of an (H, W, 3) linear RGB map at full resolution."""
    from arlight.pipeline.ibl import radiance_sh

    image = equirect.check_equirect(hdr_rgb, "hdr")
    lum = np.asarray(image, dtype=np.float32) @ LUMA.astype(np.float32)
    coeffs = radiance_sh(lum[..., None])[0]
    normals = sh.fibonacci_sphere(num_normals)
    return HdrTruth(coeffs, sh.dominant_direction(coeffs), normals, irradiance_at(lum, normals))


def best_scale(estimate: np.ndarray, truth: np.ndarray) -> float:
    """argmin_s sum (s e / E - 1)^2 = sum q / sum q^2 with q = e / E; 0 when e is all zero."""
    q = np.asarray(estimate, dtype=np.float64) / np.asarray(truth, dtype=np.float64)
    qq = float(q @ q)
    return float(q.sum() / qq) if qq > 0.0 else 0.0


def relative_irradiance_error(
    estimate: np.ndarray, truth: np.ndarray, scale: float | None = None
) -> float:
    """mean |s e - E| / E after the best scale s (or the given one)."""
    e = np.asarray(estimate, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    s = best_scale(e, t) if scale is None else scale
    return float(np.mean(np.abs(s * e - t) / t))


def sh_error(estimate: np.ndarray, truth: np.ndarray, scale: float) -> float:
    """|s c - c_true| / |c_true| over the coefficients both have."""
    n = min(len(estimate), len(truth))
    c = np.asarray(estimate[:n], dtype=np.float64)
    t = np.asarray(truth[:n], dtype=np.float64)
    return float(np.linalg.norm(scale * c - t) / np.linalg.norm(t))


def diffuse_map_at(diffuse_map: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Luminance of an (h, w, 3) irradiance map looked up bilinearly at `normals` (K,),
    as a renderer samples it."""
    lum = np.asarray(diffuse_map, dtype=np.float32) @ LUMA.astype(np.float32)
    return equirect.sample_bilinear(lum, normals).astype(np.float64)
