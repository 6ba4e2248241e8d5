"""The per-channel reductions give what NumPy's reductions over the last axis give."""

import numpy as np
import pytest

from arlight.pipeline.channels import any_nonzero, channel_max, vector_length


@pytest.fixture
def image() -> np.ndarray:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(48, 64, 3)).astype(np.float32)
    a[3, 4, 1] = np.nan
    a[5, 6] = 0.0
    a[7, 8, 2] = np.inf
    a[9, 10] = (0.0, -0.0, 0.0)
    return a


def test_channel_max_is_numpys(image):
    np.testing.assert_array_equal(channel_max(image), image.max(axis=-1))
    assert np.isnan(channel_max(image)[3, 4])  # NaN wins, as in ndarray.max
    flat = image.reshape(-1, 3)
    np.testing.assert_array_equal(channel_max(flat), flat.max(axis=1))


def test_any_nonzero_is_numpys(image):
    expected = np.any(image != 0, axis=-1)
    np.testing.assert_array_equal(any_nonzero(image), expected)
    assert not any_nonzero(image)[5, 6] and not any_nonzero(image)[9, 10]
    assert any_nonzero(image)[3, 4]  # NaN is not zero


def test_vector_length_is_numpys(image):
    d = image.astype(np.float64)
    np.testing.assert_array_equal(vector_length(d), np.linalg.norm(d, axis=-1))
    assert vector_length(np.array([3.0, 4.0])) == 5.0
    assert vector_length(image).dtype == np.float32


def test_inputs_are_not_modified(image):
    before = image.copy()
    channel_max(image), any_nonzero(image), vector_length(image)
    np.testing.assert_array_equal(image, before)
