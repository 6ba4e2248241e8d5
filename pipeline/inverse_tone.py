"""Inverse tone mapping: an 8-bit LDR panorama -> a linear HDR radiance map, per pixel.

Every operator takes an (H, W, 3) uint8 RGB image (sRGB-encoded, as cameras and video
codecs store it) and returns an (H, W, 3) float32 map of linear radiance in relative units:
1.0 is the brightness at which a linearised 8-bit channel clips (255). Absolute scale is
unknown from an LDR image; everything downstream (SH, diffuse maps, the dominant direction)
is linear in the map, so a global factor carries through unchanged.

The operators (``OPERATORS``; ``arlight ibl --operator NAME``):

``paper``
    Eq. 1-3 of the 360-video IBL paper (``../shared/seeds/001_*``) exactly, on the values
    as stored: channels c_i = value / 255 (sRGB-encoded, NOT linearised), L_i = 0.3 R_i +
    0.59 G_i + 0.11 B_i (eq. 1), L_s = 10 L_i^10 + 1.8 (eq. 2), c_o = L_s c_i (eq. 3); the
    output is used as linear radiance, as the paper feeds it to its renderer.
``paper-linear``
    The same equations on linearised channels: c_i = sRGB^-1(value / 255) first
    (IEC 61966-2-1), then eq. 1-3. The paper does not say which it did; both are measured
    (``benchmarks/ibl_truth.py``).
``linear``
    sRGB decoding alone, no expansion: the LDR map as radiance (the baseline every operator
    must beat).
``boost``
    Ours: sRGB decoding (then every unclipped pixel is the true radiance, up to the global
    scale and 8-bit quantisation), and the pixels whose three channels are all saturated
    (the white core of a light source, where the sensor lost the energy) multiplied by
    ``SATURATION_BOOST``, so that clipped light sources carry a plausible share of the
    energy instead of the clip level. "All three saturated" is a smooth weight of the
    smallest channel, 0 at ``SATURATION_START_U8`` rising to 1 at ``SATURATION_FULL_U8``
    (smoothstep): video codecs spread a clipped 255 over about 235-255 (on mp4v frames of
    the shared maps the fully clipped pixels' smallest channel has median 248, 5th
    percentile 232-240), and a smooth weight keeps a pixel that crosses a threshold from
    frame to frame from flickering. Pixels with only one or two channels clipped (coloured
    skies near the sun, sunsets) are left as decoded: on the HDR truth their luminance is
    at most about the clip level (median 0.5-1.0 of it). The factor 5 is about the
    geometric middle of the clipped cores' true mean radiance on the shared HDR maps at the
    middle exposure (1.3 to 35 times the clip, one studio light 1300) and is measured
    against the other factors in ``benchmarks/ibl_truth.py --boost-sweep``.

``DEFAULT_OPERATOR`` is the one the measurement against HDR truth favours
(docs/results/ibl.md, "Inverse tone mapping against HDR truth").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

from arlight.core.checks import check_image
from arlight.pipeline.color import srgb_to_linear

PAPER_LUMA = np.array([0.3, 0.59, 0.11], dtype=np.float32)  # eq. 1
SATURATION_START_U8 = 235  # `boost`: smallest channel where the saturation weight starts
SATURATION_FULL_U8 = 252  # ... and where it reaches 1 (fully clipped)
SATURATION_BOOST = 5.0  # `boost`: radiance of a fully clipped pixel, in clip levels


def paper_expand(values: np.ndarray) -> np.ndarray:
    """Eq. 1-3 on (..., 3) float channel values in [0, 1] -> (..., 3) float32.

    L_i = 0.3 R + 0.59 G + 0.11 B; L_s = 10 L_i^10 + 1.8; out = L_s (R, G, B). Output range
    [0, 11.8] for inputs in [0, 1].
    """
    c = np.asarray(values, dtype=np.float32)
    lum = c @ PAPER_LUMA
    scale = 10.0 * lum**10 + 1.8
    return c * scale[..., None]


def _paper(ldr: np.ndarray) -> np.ndarray:
    return paper_expand(ldr.astype(np.float32) * np.float32(1.0 / 255.0))


def _paper_linear(ldr: np.ndarray) -> np.ndarray:
    return paper_expand(srgb_to_linear(ldr))


def _linear(ldr: np.ndarray) -> np.ndarray:
    return srgb_to_linear(ldr)


def saturation_weight(
    ldr: np.ndarray, start: int = SATURATION_START_U8, full: int = SATURATION_FULL_U8
) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how fully clipped each pixel is, from its smallest channel
    (smoothstep from `start`, 0, to `full`, 1; a step at `full` when start >= full)."""
    levels = np.arange(256, dtype=np.float32)  # one weight per 8-bit level: a lookup table
    if start >= full:
        table = (levels >= full).astype(np.float32)
    else:
        t = np.clip((levels - np.float32(start)) / np.float32(full - start), 0.0, 1.0)
        table = t * t * (3.0 - 2.0 * t)
    smallest = np.minimum(np.minimum(ldr[..., 0], ldr[..., 1]), ldr[..., 2])  # 25x np.min's
    return table[smallest]


def boost_saturated(
    ldr: np.ndarray,
    boost: float = SATURATION_BOOST,
    start: int = SATURATION_START_U8,
    full: int = SATURATION_FULL_U8,
) -> np.ndarray:
    """The `boost` operator with its parameters open (for sweeps and tests): linear RGB
    times 1 + (boost - 1) w, w = `saturation_weight`.

    One pass per pixel through two 256-entry tables (the linear value of a level; the factor
    of the smallest channel's level): the same float32 values as the arrays' arithmetic
    (:func:`boost_saturated_numpy`, the oracle)."""
    image = np.ascontiguousarray(ldr, dtype=np.uint8)
    levels = np.arange(256, dtype=np.uint8)
    linear = srgb_to_linear(levels)
    factor = 1.0 + np.float32(boost - 1.0) * saturation_weight(
        np.repeat(levels[:, None], 3, axis=1), start, full
    )
    out = np.empty(image.shape, np.float32)
    _boost_kernel(image.reshape(-1, 3), linear, factor, out.reshape(-1, 3))
    return out


def boost_saturated_numpy(
    ldr: np.ndarray,
    boost: float = SATURATION_BOOST,
    start: int = SATURATION_START_U8,
    full: int = SATURATION_FULL_U8,
) -> np.ndarray:
    """:func:`boost_saturated` with NumPy arrays (the oracle of its kernel)."""
    out = srgb_to_linear(ldr)
    factor = 1.0 + np.float32(boost - 1.0) * saturation_weight(ldr, start, full)
    return out * factor[..., None]


# serial (a few ms; 2 threads lose under load): docs/results/ibl.md, "The 360 path ..."
@numba.njit(cache=True)
def _boost_kernel(pixels, linear, factor, out):
    """out[k, c] = linear[pixels[k, c]] * factor[min over c of pixels[k, c]] (float32)."""
    for k in range(pixels.shape[0]):
        r, g, b = pixels[k, 0], pixels[k, 1], pixels[k, 2]
        f = factor[min(r, min(g, b))]
        out[k, 0] = linear[r] * f
        out[k, 1] = linear[g] * f
        out[k, 2] = linear[b] * f


def _boost(ldr: np.ndarray) -> np.ndarray:
    return boost_saturated(ldr)


@dataclass(frozen=True)
class Operator:
    """One inverse tone-mapping operator: `apply(uint8 RGB) -> float32 linear RGB`."""

    name: str
    summary: str  # one line, for --help and reports
    apply: Callable[[np.ndarray], np.ndarray]


OPERATORS: dict[str, Operator] = {
    op.name: op
    for op in (
        Operator("boost", "sRGB decoded, fully clipped pixels x5 (ours)", _boost),
        Operator("paper", "eq. 1-3 on the sRGB-encoded values (the paper)", _paper),
        Operator("paper-linear", "eq. 1-3 on sRGB-decoded values", _paper_linear),
        Operator("linear", "sRGB decoded, no expansion (LDR baseline)", _linear),
    )
}
DEFAULT_OPERATOR = "boost"


def expand(ldr_rgb: np.ndarray, operator: str = DEFAULT_OPERATOR) -> np.ndarray:
    """HDR radiance map (H, W, 3) float32, linear, relative units, of an 8-bit RGB image.

    ldr_rgb: (H, W, 3) uint8 RGB, sRGB-encoded. operator: a key of ``OPERATORS``.
    """
    if operator not in OPERATORS:
        raise ValueError(
            f"unknown inverse tone-mapping operator {operator!r}; one of {', '.join(OPERATORS)}"
        )
    image = check_image(ldr_rgb, "panorama", channels=3, dtype=np.uint8)
    return OPERATORS[operator].apply(image)
