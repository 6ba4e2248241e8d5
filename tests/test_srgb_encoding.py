"""8-bit sRGB codes by table and comparison equal the definition's (a power per value)."""

from __future__ import annotations

import numpy as np

from arlight.pipeline import srgb_encoding as se


def _defined(values: np.ndarray) -> np.ndarray:
    """The definition, value by value: round(255 * srgb(clip(c))), NaN -> 0."""
    return np.array([se._srgb_code(float(c)) for c in values], np.uint8)


def test_thresholds_are_the_steps_of_the_definition():
    t = se.THRESHOLDS
    assert t.shape == (255,) and np.all(np.diff(t) > 0) and 0 < t[0] and t[-1] <= 1.0
    codes = np.arange(1, 256)
    np.testing.assert_array_equal(_defined(t), codes)
    np.testing.assert_array_equal(_defined(np.nextafter(t, -np.inf)), codes - 1)


def test_every_bin_holds_at_most_one_step():
    edges = np.arange(1, se._BINS + 1) / se._BINS
    assert np.all(np.searchsorted(se.THRESHOLDS, edges) - se.TABLE_BASE <= 1)


def test_codes_equal_the_definition_at_the_edges_and_at_random():
    rng = np.random.default_rng(0)
    bins = np.arange(se._BINS + 1) / se._BINS
    t = se.THRESHOLDS
    values = np.concatenate(
        [
            t,
            np.nextafter(t, -np.inf),
            np.nextafter(t, np.inf),
            bins,
            np.nextafter(bins, -np.inf),
            rng.random(20000),
            rng.random(20000) * 0.01,
            rng.normal(0.5, 1.0, 20000),
            [np.nan, np.inf, -np.inf, 0.0, -0.0, 1.0, 5e-324, 1e300, -1e300],
        ]
    )
    np.testing.assert_array_equal(se.linear_to_srgb_u8(values), _defined(values))


def test_image_shape_and_precision_kept():
    linear = np.linspace(0, 1, 4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    out = se.linear_to_srgb_u8(linear)
    assert out.shape == (4, 5, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out.reshape(-1), _defined(linear.astype(np.float64).ravel()))
    assert out[0, 0, 0] == 0 and out[-1, -1, -1] == 255
