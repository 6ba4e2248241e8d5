"""The pixels the light is fitted to (pipeline.fit_region): those near the look-at point."""

from __future__ import annotations

import numpy as np

from arlight.core.contracts import Confidence
from arlight.pipeline.fit_region import MIN_KEPT, blended, look_at_point, near_look_at
from arlight.pipeline.light_estimation import LightEstimate
from arlight.pipeline.transfer_upsampling import TransferSamples


def _room(width: int = 160, height: int = 120) -> np.ndarray:
    """(H, W, 3) camera-frame points: a floor patch 1.5 m ahead in the centre columns, a
    wall 6 m away elsewhere."""
    points = np.zeros((height, width, 3), np.float32)
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    x = (u - width / 2) / width
    y = (v - height / 2) / width
    centre = np.abs(u - width / 2) < width / 4
    z = np.where(centre, 1.5, 6.0)
    points[..., 0], points[..., 1], points[..., 2] = x * z, y * z, z
    return points


def _samples(points: np.ndarray) -> TransferSamples:
    v, u = np.nonzero(points[..., 2] > 0)
    k = len(v)
    return TransferSamples(v, u, np.arange(k * 4, dtype=np.float32).reshape(k, 4), np.ones(k))


def test_the_look_at_point_is_what_the_optical_axis_meets() -> None:
    centre = look_at_point(_room())
    assert centre is not None and abs(centre[2] - 1.5) < 0.05 and np.abs(centre[:2]).max() < 0.1
    assert look_at_point(np.zeros((4, 4, 3), np.float32)) is None


def test_only_the_samples_near_the_look_at_point_are_kept() -> None:
    points = _room()
    samples = _samples(points)
    near = near_look_at(samples, points, 1.0)
    kept = points[near.pixel_v, near.pixel_u]
    assert MIN_KEPT <= len(near.pixel_v) < len(samples.pixel_v)
    assert np.all(kept[:, 2] < 2.0)  # the far wall is left out, the floor patch kept
    # the rows of every array follow the pixels
    index = np.flatnonzero(
        np.isin(samples.pixel_v * 1000 + samples.pixel_u, near.pixel_v * 1000 + near.pixel_u)
    )
    np.testing.assert_array_equal(near.transfer, samples.transfer[index])
    np.testing.assert_array_equal(near.bounce, samples.bounce[index])


def test_every_sample_is_kept_when_off_or_when_too_few_would_be_left() -> None:
    points = _room()
    samples = _samples(points)
    assert near_look_at(samples, points, 0.0) is samples
    assert near_look_at(samples, points, 0.01) is samples  # a few pixels within 1 cm


def _estimate(sh: np.ndarray, bands: int) -> LightEstimate:
    return LightEstimate(
        sh=sh,
        confidence=Confidence(bands_estimated=bands, value=0.5),
        sh_rgb=np.stack([sh, 2.0 * sh, 3.0 * sh]),
    )


def test_the_blend_mixes_only_the_bands_both_fits_estimated() -> None:
    """blended: (1 - s) near + s whole over the bands both solved for; the near fit's other
    bands (zero where it solved fewer) and its confidence stay."""
    rng = np.random.default_rng(0)
    whole = _estimate(rng.normal(size=16), 4)
    near_sh = np.zeros(16)
    near_sh[0] = 1.0
    near = _estimate(near_sh, 1)  # band 0 alone: a flat view
    out = blended(near, whole, 0.5)
    assert out.sh[0] == 0.5 * 1.0 + 0.5 * whole.sh[0]
    assert not np.any(out.sh[1:])  # nothing beyond the band the near fit estimated
    assert out.confidence is near.confidence
    np.testing.assert_allclose(out.sh_rgb, np.stack([out.sh, 2.0 * out.sh, 3.0 * out.sh]))
    near4 = _estimate(rng.normal(size=16), 4)
    np.testing.assert_allclose(blended(near4, whole, 0.25).sh, 0.75 * near4.sh + 0.25 * whole.sh)
