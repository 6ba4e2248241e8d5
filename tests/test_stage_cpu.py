"""benchmarks/stage_cpu.py: the checkpoint hook splits a frame into its stages."""

import time

import numpy as np
from conftest import SMALL

from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.sources.synthetic import make_sequence
from benchmarks.stage_cpu import SEGMENTS, StageClock


def test_segments_add_up_to_the_frame():
    scene = make_sequence(num_frames=2, width=80, height=60)
    pipeline = Pipeline(Config.from_preset("fast", **SMALL), scene.camera)
    pipeline.process(scene.frames[0])
    clock = StageClock()
    t0 = time.perf_counter()
    pipeline.process(scene.frames[1], checkpoint=clock)
    clock.finish()
    total = time.perf_counter() - t0
    wall = clock.wall[: len(SEGMENTS)]
    assert np.all(wall >= 0.0) and np.all(clock.cpu >= 0.0)
    assert wall[SEGMENTS.index("Reconstruct+Surface")] > 0.0
    assert wall[SEGMENTS.index("LightEst")] > 0.0
    assert abs(wall.sum() - total) < 0.05 * total + 0.005
