"""LightEst as a session keeps it (pipeline.light_stage): a LightFrame in, a LightOutcome out.

A synthetic frame: random unit normals at the pixels of a small image, the visibility-free
transfer A_l Y_lm(n) (what radiance transfer gives without occlusion), one grey albedo, and
the image I = T l of a known light. The stage is driven without a Pipeline: the typed frame
is all it reads.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from arlight.core.frames import Diagnostics
from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh
from arlight.pipeline.compact_light import CompactSource
from arlight.pipeline.config import Config
from arlight.pipeline.light_stage import LightFrame, LightStage
from arlight.pipeline.radiance_transfer import TransferSamples

UP = np.array([0.0, 1.0, 0.0])  # world "up" (the pose is the identity: world = camera)
LAMBERT_PER_COEFF = np.repeat(sh.lambert_band_factors(4), [1, 3, 5, 7])


def _light(direction, intensity: float = 0.6, ambient: float = 0.3) -> np.ndarray:
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    coeffs = sh.directional_light(d, intensity, 4)
    coeffs[0] += ambient
    return coeffs


def _frame(light: np.ndarray, height: int = 60, width: int = 80, seed: int = 0) -> LightFrame:
    """Every pixel a sample: normals of the upper hemisphere (a scene lit from above a
    floor), points 2 m ahead, the image of `light` under the plain transfer."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(height * width, 3))
    n[:, 1] = np.abs(n[:, 1])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    transfer = (sh.sh_basis(n, 4) * LAMBERT_PER_COEFF).astype(np.float32)
    v, u = np.divmod(np.arange(height * width), width)
    colour = np.repeat(np.clip(transfer @ light, 0.0, None)[:, None], 3, axis=1) / np.pi
    points = np.zeros((height, width, 3), np.float32)
    points[..., 2] = 2.0
    return LightFrame(
        transfer=TransferSamples(v, u, transfer, None),
        points=points,
        normals=n.reshape(height, width, 3).astype(np.float32),
        up_world=UP,
        color_linear=colour.reshape(height, width, 3).astype(np.float32),
        labels=None,
        pose=np.eye(4),
    )


def _stage(**overrides) -> LightStage:
    config = Config.from_preset("full", compact_sources=0, fit_radius_m=0.0, **overrides)
    return LightStage(config, work_width=80)


def _never_abandoned(stage: str) -> None:
    assert stage == "LightEst"


def test_one_frame_reports_the_light_above_the_horizon() -> None:
    light = _light((0.4, 0.8, 0.3))
    stage = _stage()
    diagnostics: Diagnostics = {}
    out = stage.run(_frame(light), _never_abandoned, diagnostics)
    truth = sh.above_horizon_direction(light, UP)
    assert angular_error_deg(out.direction_world, truth) < 5.0
    assert abs(np.linalg.norm(out.direction_world) - 1.0) < 1e-9
    assert out.confidence.value > 0.0 and out.intensity > 0.0
    assert out.disagreement_deg == 0.0  # one fit: no whole-view fit without compact sources
    assert "compact" not in diagnostics  # nothing searched
    # what the next frame and the aux buffer's light read
    assert stage.up_world is UP
    np.testing.assert_array_equal(stage.light_world, out.direction_world)
    notes = stage.diagnostics_of(out)
    assert notes["support_plane_up_world"] == [0.0, 1.0, 0.0]
    assert notes["fit_disagreement_deg"] == 0.0
    assert notes["sh_direction_world"] == [float(x) for x in out.direction_world]  # no source
    assert notes["bands_requested"] == 4


def test_the_filter_carries_the_light_from_frame_to_frame() -> None:
    """A light that moves is followed gradually (the temporal filter), and at once with the
    filter off (temporal_half_life_frames 0)."""
    first, second = _light((0.6, 0.7, 0.0)), _light((-0.6, 0.7, 0.0))
    moved = sh.above_horizon_direction(second, UP)
    smoothed, unfiltered = _stage(), _stage(temporal_half_life_frames=0.0)
    for stage in (smoothed, unfiltered):
        stage.run(_frame(first), _never_abandoned, {})
    lagging = smoothed.run(_frame(second, seed=1), _never_abandoned, {})
    following = unfiltered.run(_frame(second, seed=1), _never_abandoned, {})
    assert angular_error_deg(following.direction_world, moved) < 5.0
    assert angular_error_deg(lagging.direction_world, moved) > 10.0
    # the raw direction (before the filter) is this frame's own either way
    assert angular_error_deg(lagging.raw_direction, moved) < 5.0


def test_a_kept_source_is_reported_and_the_sh_keeps_its_own_direction() -> None:
    """With a compact source kept, the reported direction is the source's; the SH's own
    (the filtered coefficients' direction) travels beside it in the diagnostics."""
    light = _light((0.4, 0.8, 0.3))
    stage = _stage()
    sun = np.array([-0.6, 0.5, -0.62])
    sun /= np.linalg.norm(sun)
    source = CompactSource(sun, 0.5, None, 0.5, 0.6, 0.2)
    stage.kept_source = lambda: source  # type: ignore[method-assign]
    out = stage.run(_frame(light), _never_abandoned, {})
    np.testing.assert_array_equal(out.direction_world, sun)
    np.testing.assert_array_equal(out.raw_direction, sun)
    np.testing.assert_allclose(out.sh_direction_world, stage.light_direction(out.coeffs))
    assert angular_error_deg(out.sh_direction_world, sh.above_horizon_direction(light, UP)) < 5
    assert angular_error_deg(out.sh_direction_world, out.direction_world) > 30.0
    notes = stage.diagnostics_of(out)
    assert notes["sh_direction_world"] == [float(x) for x in out.sh_direction_world]
    assert notes["raw_dominant_direction_world"] == [float(x) for x in sun]


def test_a_frame_without_samples_reports_no_direction() -> None:
    frame = _frame(_light((0.4, 0.8, 0.3)))
    empty = TransferSamples(
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 16), np.float32), None
    )
    out = _stage().run(
        LightFrame(
            empty,
            frame.points,
            frame.normals,
            None,
            frame.color_linear,
            None,
            frame.pose,
        ),
        _never_abandoned,
        {},
    )
    assert not np.any(out.direction_world) and out.intensity == 0.0
    assert out.confidence.value == 0.0 and out.confidence.reason == "no valid depth"


def test_the_checkpoint_can_abandon_the_fit() -> None:
    """A server's per-frame deadline raises from `check` between the fit's passes."""

    class Deadline(Exception):
        pass

    def deadline(stage: str) -> None:
        raise Deadline(stage)

    frame = _frame(_light((0.4, 0.8, 0.3)))
    halves = np.zeros(frame.points.shape[:2], np.int64)
    halves[:, 40:] = 1  # two material segments: the albedo alternation runs its passes
    with pytest.raises(Deadline, match="LightEst"):
        _stage().run(dataclasses.replace(frame, labels=halves), deadline, {})
