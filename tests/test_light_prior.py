"""The light prior learned from HDR maps (pipeline/light_prior.py): its algebra and its data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import DATA, needs_data

from arlight.pipeline import sh
from arlight.pipeline.light_prior import map_moments, pooled, prior_matrix


def _rotation_about(axis, angle) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


class TestPriorMatrix:
    def test_symmetric_positive_semidefinite(self):
        p = prior_matrix(np.array([0.0, 1.0, 0.0]), 4)
        assert np.allclose(p, p.T)
        assert np.linalg.eigvalsh(p).min() > -1e-8

    def test_zero_at_the_mean_light_of_any_brightness(self):
        mean, _ = pooled()
        p = prior_matrix(np.array([0.0, 1.0, 0.0]), 4)
        for scale in (0.1, 1.0, 50.0):
            assert (scale * mean) @ p @ (scale * mean) == pytest.approx(0.0, abs=1e-6 * scale**2)

    def test_follows_the_support_plane(self):
        """A light rotated with the up vector costs the same: the prior is about 'up'."""
        up = np.array([0.3, 0.9, -0.2])
        up /= np.linalg.norm(up)
        r = _rotation_about(np.cross([0, 1, 0], up), math.acos(up[1]))
        light = np.random.default_rng(1).normal(size=16)
        light[0] = 3.0
        cost_y = light @ prior_matrix(np.array([0.0, 1.0, 0.0]), 4) @ light
        rotated = sh.rotate(light, r)
        assert rotated @ prior_matrix(up, 4) @ rotated == pytest.approx(cost_y, rel=1e-6)

    def test_heading_does_not_matter(self):
        light = np.random.default_rng(2).normal(size=16)
        light[0] = 2.0
        p = prior_matrix(np.array([0.0, 1.0, 0.0]), 4)
        turned = sh.rotate(light, _rotation_about([0, 1, 0], 1.1))
        # exact in theory (36 headings average bands <= 3 exactly); the shipped 7-digit
        # moments and the inverse covariance leave ~1e-6
        assert turned @ p @ turned == pytest.approx(light @ p @ light, rel=1e-4)

    def test_light_from_below_costs_more_than_from_above(self):
        above = sh.directional_light(
            np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5]), 1.0, 4
        ) + sh.project(lambda d: np.full(len(d), 0.2), 4)
        below = above.copy()
        below[[1, 5, 9, 11, 13]] *= -1  # mirrored through the horizon plane (y -> -y)
        p = prior_matrix(np.array([0.0, 1.0, 0.0]), 4)
        assert below @ p @ below > above @ p @ above

    def test_fewer_bands_are_the_marginal(self):
        assert prior_matrix(np.array([0.0, 1.0, 0.0]), 2).shape == (4, 4)
        assert not np.any(prior_matrix(np.array([0.0, 1.0, 0.0]), 1))


class TestLeaveMapsOut:
    def test_26_maps_ship(self):
        assert len(map_moments()) == 26

    def test_excluding_a_map_changes_the_prior_and_names_work_with_or_without_suffix(self):
        full, _ = pooled()
        a, _ = pooled(frozenset({"kiara_1_dawn_1k"}))
        b, _ = pooled(frozenset({"kiara_1_dawn"}))
        assert np.allclose(a, b) and not np.allclose(a, full)

    def test_excluding_every_map_is_an_error(self):
        with pytest.raises(ValueError, match="light_prior_exclude"):
            pooled(frozenset(map_moments()))

    @pytest.mark.data
    @needs_data(DATA / "hdri")
    def test_shipped_numbers_regenerate_from_the_maps(self, tmp_path):
        import json

        from arlight.synth.light_prior import main

        assert main(["--maps-dir", str(DATA / "hdri"), "--out", str(tmp_path / "p.json")]) == 0
        made = json.loads((tmp_path / "p.json").read_text())["maps"]
        for name, (mean, second) in map_moments().items():
            assert np.allclose(made[name]["mean"], mean, atol=1e-6)
            assert np.allclose(made[name]["second_moment"], second, atol=1e-6)
