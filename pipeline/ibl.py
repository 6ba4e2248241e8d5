"""Image-based lighting from one HDR panorama: SH radiance, diffuse map, dominant direction.

Everything is in the panorama's frame (``pipeline/equirect.py``: +y up, u = atan2(x, -z) /
2 pi, v = acos(y) / pi) and per frame, without pre-computation across frames (the paper's
"no precomputation": every frame of a video is processed on its own).

- ``sh_rgb`` (3, bands^2): radiance SH per linear RGB channel, the project's convention
  (``pipeline/sh.py``: real, orthonormal, no Condon-Shortley phase, index l(l+1)+m),
  c = sum over pixels of L(w) Y(w) d_omega on the map area-averaged to ``sh_source_size``;
  ``sh`` (bands^2,) = the luminance (``color.LUMA``) of it (SH are linear in the map).
- The diffuse map (the paper's section 3.1, after Miller and Hoffman): per pixel direction n
  of a ``diffuse_size`` map, the irradiance E(n) = integral L(w) max(0, n . w) d_omega, by
  brute force over every pixel of the map area-averaged to ``diffuse_source_size`` (by
  default the output's own size, as the paper computes it); a Lambertian surface of albedo
  rho facing n reflects rho E(n) / pi. Units: the map's radiance times steradians.
  The fast path (``diffuse_method="sh"``): E from the SH by the Ramamoorthi-Hanrahan
  convolution (``sh.irradiance_from_radiance``), evaluated at the same pixel directions.
- ``dominant_direction``: ``sh.dominant_direction(sh)``, normalize(integral L(w) w dw), the
  first moment of the luminance: the definition of the HDR truth and of the RGB-D path, and
  a direction that changes smoothly when several lamps of similar brightness trade places
  (a brightest-region estimate jumps between them; ``brightest_direction`` is kept as the
  comparator that ``benchmarks/ibl_truth.py`` measures against the same truth).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from arlight.pipeline import equirect, sh
from arlight.pipeline.color import LUMA
from arlight.pipeline.inverse_tone import DEFAULT_OPERATOR, OPERATORS, expand

DIFFUSE_METHODS = ("brute-force", "sh")
MAX_DIFFUSE_HEIGHT = 256  # a 512x256 brute-force map needs a (131072 x 131072) kernel: 64 GiB


@dataclass(frozen=True)
class IblParams:
    """Parameters of the per-frame path; sizes are (width, height), 2:1, pixels."""

    operator: str = DEFAULT_OPERATOR  # inverse tone mapping (pipeline/inverse_tone.py)
    diffuse_size: tuple[int, int] = (32, 16)  # the diffuse map (the paper's default)
    diffuse_source_size: tuple[int, int] | None = None  # brute-force input; None = diffuse_size
    diffuse_method: str = "brute-force"  # or "sh" (Ramamoorthi-Hanrahan, the fast path)
    sh_source_size: tuple[int, int] = (128, 64)  # the map area-averaged to this for the SH
    bands: int = 4  # SH bands l = 0..bands-1 (16 coefficients)

    def __post_init__(self) -> None:
        if self.operator not in OPERATORS:
            raise ValueError(
                f"operator must be one of {', '.join(OPERATORS)}, got {self.operator!r}"
            )
        if self.diffuse_method not in DIFFUSE_METHODS:
            raise ValueError(
                f"diffuse_method must be one of {', '.join(DIFFUSE_METHODS)}, "
                f"got {self.diffuse_method!r}"
            )
        for name in ("diffuse_size", "diffuse_source_size", "sh_source_size"):
            size = getattr(self, name)
            if size is None:
                continue
            w, h = size
            if w != 2 * h or h < 1:
                raise ValueError(f"{name} must be 2:1 (W = 2 H), got {w}x{h}")
            if name != "sh_source_size" and h > MAX_DIFFUSE_HEIGHT:
                raise ValueError(
                    f"{name} must be at most {2 * MAX_DIFFUSE_HEIGHT}x"
                    f"{MAX_DIFFUSE_HEIGHT} (a brute-force kernel grows as the "
                    f"4th power of the height), got {w}x{h}"
                )
        if self.bands < 2:
            raise ValueError(f"bands must be >= 2 (band 1 carries the direction), got {self.bands}")

    @property
    def brute_force_source(self) -> tuple[int, int]:
        return self.diffuse_source_size or self.diffuse_size


@dataclass
class IblResult:
    """One frame's lighting, in the panorama's frame."""

    sh: np.ndarray  # (bands^2,) luminance radiance SH
    sh_rgb: np.ndarray  # (3, bands^2) radiance SH per linear RGB channel
    dominant_direction: np.ndarray  # (3,) unit, towards the light; zeros for a black map
    diffuse_map: np.ndarray  # (h, w, 3) float32 irradiance E(n) per pixel direction n
    timings_ms: dict[str, float] = field(default_factory=dict)
    hdr: np.ndarray | None = None  # (H, W, 3) float32 the HDR map itself (its radiance)


def _fit_size(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The map area-averaged down to `size`, or as it is when it is not larger."""
    w, h = size
    if image.shape[0] <= h:
        return image
    return equirect.downsample(image, w, h)


@lru_cache(maxsize=8)
def _weighted_basis(height: int, width: int, bands: int) -> np.ndarray:
    """(H*W, bands^2) float32: Y(w_k) d_omega_k of every pixel of an (H, W) map."""
    dirs = equirect.pixel_directions(height, width).reshape(-1, 3)
    omega = equirect.pixel_solid_angles(height, width).reshape(-1, 1)
    out = (sh.sh_basis(dirs, bands) * omega).astype(np.float32)
    out.setflags(write=False)
    return out


def radiance_sh(hdr: np.ndarray, bands: int = 4) -> np.ndarray:
    """(C, bands^2) float64 radiance SH of an (H, W, C) equirectangular map, every pixel.

    c_i = sum_k L(w_k) Y_i(w_k) d_omega_k over the pixel centres (exact solid angles).
    """
    image = equirect.check_equirect(hdr, "hdr")
    h, w = image.shape[:2]
    values = np.asarray(image, dtype=np.float32).reshape(h * w, -1)
    return (values.T @ _weighted_basis(h, w, bands)).astype(np.float64)


@lru_cache(maxsize=4)
def _cosine_kernel(out_size: tuple[int, int], source_size: tuple[int, int]) -> np.ndarray:
    """(h*w, H*W) float32: max(0, n_j . w_k) d_omega_k, output pixel j, source pixel k."""
    normals = equirect.pixel_directions(out_size[1], out_size[0]).reshape(-1, 3)
    dirs = equirect.pixel_directions(source_size[1], source_size[0]).reshape(-1, 3)
    omega = equirect.pixel_solid_angles(source_size[1], source_size[0]).reshape(1, -1)
    kernel = (np.maximum(normals @ dirs.T, 0.0) * omega).astype(np.float32)
    kernel.setflags(write=False)
    return kernel


def diffuse_map_brute_force(
    hdr: np.ndarray, size: tuple[int, int] = (32, 16), source_size: tuple[int, int] | None = None
) -> np.ndarray:
    """Irradiance map (h, w, C) float32 at `size` by brute force over the map at `source_size`.

    hdr: (H, W, C) linear radiance, equirectangular; area-averaged to `source_size` (default
    `size`; not enlarged when already smaller). Every output pixel direction n gets
    sum_k L(w_k) max(0, n . w_k) d_omega_k: O((h w) (H' W')) operations, one matrix product.
    """
    image = equirect.check_equirect(hdr, "hdr")
    src = _fit_size(np.asarray(image, dtype=np.float32), source_size or size)
    sh_, sw = src.shape[:2]
    channels = 1 if src.ndim == 2 else src.shape[2]
    kernel = _cosine_kernel((int(size[0]), int(size[1])), (sw, sh_))
    out = kernel @ src.reshape(sh_ * sw, channels)
    return (
        out.reshape(size[1], size[0], channels) if src.ndim == 3 else out.reshape(size[1], size[0])
    )


@lru_cache(maxsize=8)
def _basis_at_pixels(height: int, width: int, bands: int) -> np.ndarray:
    out = sh.sh_basis(equirect.pixel_directions(height, width).reshape(-1, 3), bands)
    out.setflags(write=False)
    return out


def diffuse_map_sh(sh_rgb: np.ndarray, size: tuple[int, int] = (32, 16)) -> np.ndarray:
    """Irradiance map (h, w, C) float32 from radiance SH (C, n): the Ramamoorthi-Hanrahan
    convolution (``sh.irradiance_from_radiance``) evaluated at the pixel directions."""
    c = np.atleast_2d(np.asarray(sh_rgb, dtype=np.float64))
    irr = sh.irradiance_from_radiance(c)
    basis = _basis_at_pixels(int(size[1]), int(size[0]), sh.bands_of(c.shape[-1]))
    return (basis @ irr.T).astype(np.float32).reshape(size[1], size[0], c.shape[0])


def brightest_direction(hdr: np.ndarray, size: tuple[int, int] = (32, 16)) -> np.ndarray:
    """The comparator: unit direction of the brightest pixel (luminance) of the map
    area-averaged to `size` (a brightest-region estimate); zeros for a black map."""
    image = equirect.check_equirect(hdr, "hdr")
    small = _fit_size(np.asarray(image, dtype=np.float32), size)
    lum = small @ LUMA.astype(np.float32) if small.ndim == 3 else small
    if not np.any(lum > 0):
        return np.zeros(3)
    i, j = np.unravel_index(int(np.argmax(lum)), lum.shape)
    return np.array(equirect.pixel_directions(*lum.shape)[i, j])


def lighting_from_hdr(hdr: np.ndarray, params: IblParams | None = None) -> IblResult:
    """SH, diffuse map and dominant direction of one linear HDR panorama (H, W, 3)."""
    p = params or IblParams()
    image = equirect.check_equirect(hdr, "hdr")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"hdr: expected an (H, W, 3) RGB map, got shape {image.shape}")
    image = np.asarray(image, dtype=np.float32)
    if not np.all(np.isfinite(image)) or image.min() < 0.0:  # radiance is finite and >= 0
        image = np.maximum(np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    sh_src = _fit_size(image, p.sh_source_size)
    t1 = time.perf_counter()
    sh_rgb = radiance_sh(sh_src, p.bands)
    sh_lum = LUMA @ sh_rgb
    t2 = time.perf_counter()
    if p.diffuse_method == "sh":
        diffuse = diffuse_map_sh(sh_rgb, p.diffuse_size)
    else:
        # the brute-force source from the smallest map that is at least as large
        src_size = p.brute_force_source
        base = sh_src if sh_src.shape[0] >= src_size[1] else image
        diffuse = diffuse_map_brute_force(base, p.diffuse_size, src_size)
    t3 = time.perf_counter()
    timings["Downsample"] = (t1 - t0) * 1e3
    timings["SH"] = (t2 - t1) * 1e3
    timings["Diffuse"] = (t3 - t2) * 1e3
    return IblResult(
        sh=sh_lum,
        sh_rgb=sh_rgb,
        dominant_direction=sh.dominant_direction(sh_lum),
        diffuse_map=diffuse,
        timings_ms=timings,
    )


def lighting_from_ldr(ldr_rgb: np.ndarray, params: IblParams | None = None) -> IblResult:
    """Inverse tone mapping (``params.operator``) then :func:`lighting_from_hdr`.

    ldr_rgb: (H, W, 3) uint8 RGB, sRGB-encoded, equirectangular (W = 2 H).
    """
    p = params or IblParams()
    equirect.check_equirect(ldr_rgb, "panorama")
    t0 = time.perf_counter()
    hdr = expand(ldr_rgb, p.operator)
    expand_ms = (time.perf_counter() - t0) * 1e3
    result = lighting_from_hdr(hdr, p)
    result.timings_ms = {"InverseTone": expand_ms, **result.timings_ms}
    result.hdr = hdr
    return result


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two vectors; nan when either is zero."""
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na == 0.0 or nb == 0.0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(np.dot(a, b) / (na * nb), -1.0, 1.0))))
