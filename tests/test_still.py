"""A camera held still (pipeline/still.py): what may be reused, and that it is reused only
then, with the light still followed."""

import math

import numpy as np
import pytest

from arlight import evaluation
from arlight.pipeline.config import Config, ReuseParams
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.still import StillCamera, block_depth, depth_change, pose_change
from arlight.sources.synthetic import make_sequence


def _pose(tx: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[0, 3] = tx
    return pose


class TestStillCamera:
    def test_pose_change_in_metres_and_degrees(self):
        t, r = pose_change(_pose(), _pose(0.003, 0.2))
        assert t == pytest.approx(0.003) and r == pytest.approx(0.2, abs=1e-6)

    def test_reuse_while_still_for_at_most_n_frames(self):
        still = StillCamera(ReuseParams(still_reuse_frames=3))
        assert not still.may_reuse(_pose())  # nothing done yet
        still.did_work(_pose())
        assert [still.may_reuse(_pose(0.001, 0.1)) for _ in range(4)] == [True] * 3 + [False]
        still.did_work(_pose())
        assert still.may_reuse(_pose())

    def test_no_reuse_once_the_camera_moves_or_turns(self):
        still = StillCamera(ReuseParams())
        still.did_work(_pose())
        assert not still.may_reuse(_pose(0.01))  # 1 cm > 5 mm
        assert not still.may_reuse(_pose(0.0, 1.0))  # 1 deg > 0.5 deg

    def test_zero_frames_turns_reuse_off(self):
        still = StillCamera(ReuseParams(still_reuse_frames=0))
        still.did_work(_pose())
        assert not still.may_reuse(_pose())

    def test_a_change_of_the_depth_image_stops_reuse(self):
        depth = np.full((48, 64), 2.0, np.float32)
        still = StillCamera(ReuseParams(), with_depth=True)
        still.did_work(_pose(), depth)
        noisy = depth + np.random.default_rng(0).normal(0, 0.01, depth.shape).astype(np.float32)
        assert still.may_reuse(_pose(), noisy)  # sensor noise averages out in 8x8 blocks
        hand = depth.copy()
        hand[10:30, 10:30] = 0.5  # something came into view
        assert depth_change(block_depth(depth), block_depth(hand)) > 0.1
        assert not still.may_reuse(_pose(), hand)


def _errors_and_reuse(config: Config, seq) -> tuple[list[float], list[dict]]:
    pipeline = Pipeline(config, seq.camera)
    errors, reused = [], []
    for frame, truth in zip(seq.frames, evaluation.scene_truth(seq), strict=True):
        out = pipeline.process(frame)
        errors.append(
            evaluation.angular_error_deg(out.dominant_direction_camera, truth.dominant_upper_camera)
        )
        reused.append(out.diagnostics["reused"])
    return errors, reused


class TestPipelineReuse:
    @pytest.fixture(scope="class")
    @classmethod
    def held(cls):
        """The built-in scene, 160 x 120, a camera held still, the sun moving at frame 4."""
        return make_sequence(num_frames=8, width=160, height=120, held=True, light_change_frame=4)

    def test_a_held_camera_reuses_and_follows_the_light(self, held):
        # `fast`'s segments at their former size: at 160 x 120 its finer ones (decision 0059)
        # are a few pixels of a 40 x 30 grid, and the reused normals move the estimate by up
        # to 5 degrees after the light change; at 640 x 480 by 1.9 (the decision's record).
        # The SH fit alone: what is reused is its geometry and transfer (a compact source's
        # direction comes from the depth mesh and its search runs one frame in five)
        config = Config.from_preset("fast", segment_coarseness=1.0, compact_sources=0)
        errors, reused = _errors_and_reuse(config, held)
        assert not any(reused[0].values())
        assert all(r["Surface"] and r["RadTransfer"] for r in reused[1:])
        fresh, _ = _errors_and_reuse(config.replace(still_reuse_frames=0), held)
        # the same estimates as without reuse, frame by frame (within the sensor noise the
        # reused geometry leaves out: its normals are smoothed over 4 pixels at 160 x 120),
        # before and after the sun moved by 110 degrees of azimuth at frame 4 (an estimate
        # that stayed behind would be ~100 degrees off; both are 5-10 degrees off the truth
        # but on frame 4, the change itself, where both are about 60 off and the noise is
        # amplified: there within 10 %)
        change = 4
        np.testing.assert_allclose(np.delete(errors, change), np.delete(fresh, change), atol=3.0)
        assert abs(errors[change] - fresh[change]) < 0.1 * fresh[change]
        assert max(errors[change + 1 :]) < 45.0

    def test_an_orbiting_camera_never_reuses(self):
        seq = make_sequence(num_frames=3, width=160, height=120)
        _, reused = _errors_and_reuse(Config.from_preset("fast"), seq)
        assert not any(any(r.values()) for r in reused)

    def test_something_entering_the_view_stops_the_transfer_reuse(self, held):
        frames = list(held.frames[:3])
        entered = frames[2].depth.copy()
        entered[20:80, 40:120] = entered[20:80, 40:120] // 2  # an object at half the depth
        frames[2] = type(frames[2])(**{**frames[2].__dict__, "depth": entered})
        pipeline = Pipeline(Config.from_preset("fast"), held.camera)
        reused = [pipeline.process(f).diagnostics["reused"] for f in frames]
        assert reused[1]["RadTransfer"] and reused[2]["Surface"]
        assert not reused[2]["RadTransfer"]


def test_aux_buffers_are_not_rendered_when_nothing_reads_them():
    seq = make_sequence(num_frames=1, width=160, height=120)
    for visibility, rendered in ((True, True), (False, False)):
        pipeline = Pipeline(Config.from_preset("fast", visibility=visibility), seq.camera)
        assert pipeline._volume.aux_params.aux_buffers is rendered
