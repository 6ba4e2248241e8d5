"""Material segments (pipeline/segmentation.py): regions of one albedo, not of one light."""

import numpy as np
import pytest

from arlight.pipeline.segmentation import material_segments

SUN = np.array([1.0, 0.86, 0.67])  # ~5000 K direct light, linear sRGB
SKY = np.array([0.73, 0.83, 1.0]) * 0.25  # ~10000 K, dimmer sky light in the shadow


def _scene():
    """A 120 x 160 grey floor (one albedo) with a sky-lit shadow band, a red box and a flat
    depth ramp (no depth edges between the regions); 2 % sensor noise."""
    h, w = 120, 160
    albedo = np.full((h, w, 3), 0.45)
    albedo[20:60, 100:140] = [0.5, 0.06, 0.05]  # red box face
    light = np.broadcast_to(SUN, (h, w, 3)).copy()
    light[70:110, 20:90] = SKY  # cast shadow on the floor
    depth = np.linspace(1.5, 3.0, h, dtype=np.float32)[:, None].repeat(w, axis=1)
    noise = 1.0 + 0.02 * np.random.default_rng(0).standard_normal((h, w, 3))
    return (albedo * light * noise).astype(np.float32), depth


def _same(labels, a, b):
    return labels[a] == labels[b]


def test_invariant_features_keep_a_sky_lit_shadow_with_its_floor():
    color, depth = _scene()
    labels = material_segments(color, depth, features="invariant")
    assert _same(labels, (90, 50), (10, 10))  # shadow and sun-lit floor: one material
    assert not _same(labels, (40, 120), (10, 10))  # the red box is not the floor


def test_chroma_features_split_the_shadow_off():
    color, depth = _scene()
    labels = material_segments(color, depth, features="chroma")
    assert not _same(labels, (90, 50), (10, 10))
    assert not _same(labels, (40, 120), (10, 10))


def test_unknown_features_are_refused():
    color, depth = _scene()
    with pytest.raises(ValueError, match="features"):
        material_segments(color, depth, features="hue")
