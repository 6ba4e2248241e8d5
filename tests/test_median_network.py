"""The row-wise selection network behind the depth filter's D'' and D''' on the CPU."""

from __future__ import annotations

import numpy as np
import pytest

from arlight.pipeline import depth_filter as df
from arlight.pipeline.median_network import (
    MAX_NETWORK_INPUTS,
    median_network,
    support_median_rows,
)


def _apply(network: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = values.copy()
    for i, j in network:
        out[i], out[j] = min(out[i], out[j]), max(out[i], out[j])
    return out


@pytest.mark.parametrize("m", range(1, MAX_NETWORK_INPUTS + 1))
def test_network_puts_the_lower_median_in_the_middle(m):
    rng = np.random.default_rng(m)
    network = median_network(m)
    assert network.ndim == 2 and (network[:, 0] < network[:, 1]).all() and (network < m).all()
    for _ in range(300):  # few distinct values: ties everywhere, as the 0-1 principle needs
        values = rng.integers(0, 4, m).astype(np.float32)
        assert _apply(network, values)[(m - 1) // 2] == np.sort(values)[(m - 1) // 2]


def test_network_is_pruned_to_the_median():
    """Median of 25 (D''): far fewer comparators than a full sort of 32 (191)."""
    assert len(median_network(25)) < 120
    assert len(median_network(1)) == 0


@pytest.mark.parametrize("m", [0, MAX_NETWORK_INPUTS + 1])
def test_network_size_out_of_range(m):
    with pytest.raises(ValueError, match="1..32"):
        median_network(m)


def _per_pixel(depth, intensity, offsets, lam_i, gate):
    out = np.empty_like(depth)
    df._support_median_cpu(depth, intensity, offsets, np.float32(lam_i), gate, out)
    return out


def _rows(depth, intensity, offsets, lam_i):
    out = np.empty_like(depth)
    network = median_network(offsets.size**2)
    support_median_rows(depth, intensity, offsets, np.float32(lam_i), network, out)
    return out


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (7, 5), (31, 43)])
@pytest.mark.parametrize("window,subsample", [(8, 5), (2, None), (3, None), (4, 4), (9, 1)])
@pytest.mark.parametrize("hole_fraction", [0.0, 0.4, 0.9, 1.0])
def test_rows_equal_the_per_pixel_kernel(shape, window, subsample, hole_fraction):
    """Bit for bit, gated and not, with image borders wider than the image and any count
    of missing candidates (a median of n valid samples, n = 0 .. m)."""
    rng = np.random.default_rng(window * 100 + shape[1])
    depth = rng.uniform(0.3, 4.0, shape).astype(np.float32)
    depth[rng.random(shape) < hole_fraction] = 0
    intensity = (rng.integers(0, 8, shape) * 4.0).astype(np.float32)
    offsets = df._window_offsets(window, subsample)
    np.testing.assert_array_equal(
        _rows(depth, intensity, offsets, 7.0), _per_pixel(depth, intensity, offsets, 7.0, True)
    )
    np.testing.assert_array_equal(
        _rows(depth, depth, offsets, np.inf), _per_pixel(depth, depth, offsets, 0.0, False)
    )


def test_all_missing_gives_zero_and_one_sample_gives_it():
    depth = np.zeros((5, 6), np.float32)
    offsets = df._window_offsets(8, 5)
    np.testing.assert_array_equal(_rows(depth, depth, offsets, np.inf), 0)
    depth[2, 3] = 1.25
    out = _rows(depth, depth, offsets, np.inf)
    assert set(np.unique(out)) == {0.0, np.float32(1.25)}
    assert out[2, 3] == np.float32(1.25)
