"""Accuracy against ground truth on ../shared/data/synthetic, pinned so it cannot regress.

Runs the `full` and `fast` presets over the first FRAMES frames of all 15 sequences with the
ground-truth poses and checks, against the light that can reach the scene
(`dominant_dir_upper_camera`), the median of the per-sequence median angular errors and the
90th percentile over all those frames: each at most the figure measured with
`benchmarks/accuracy.py --configs full fast --max-frames 4` plus a 3 degree margin. The
issue's medians (10 / 12 degrees) are met on all frames (10.0 / 10.5), its 20 degree p90 is
not: the pins hold what is.
"""

import numpy as np
import pytest
from conftest import DATA, needs_data

from arlight.pipeline.config import Config
from benchmarks.accuracy import evaluate_sequence

SYNTHETIC = DATA / "synthetic"  # the shared ground-truth sequences

FRAMES = 4
MARGIN_DEG = 3.0
# measured (degrees): median of the per-sequence medians, 90th percentile over all frames
MEASURED_DEG = {"full": (8.3, 27.2), "fast": (8.4, 33.1)}

pytestmark = [pytest.mark.slow, pytest.mark.data, needs_data(SYNTHETIC)]


@pytest.mark.parametrize("preset", sorted(MEASURED_DEG))
def test_angular_error_does_not_regress(preset):
    sequences = sorted(p for p in SYNTHETIC.iterdir() if (p / "lighting_gt.json").is_file())
    assert len(sequences) == 15
    errors = [evaluate_sequence(folder, Config.from_preset(preset), FRAMES) for folder in sequences]
    every = np.concatenate(errors)
    assert np.all(np.isfinite(every))
    median_of_medians = float(np.median([np.median(e) for e in errors]))
    p90 = float(np.percentile(every, 90))
    measured_median, measured_p90 = MEASURED_DEG[preset]
    assert median_of_medians <= measured_median + MARGIN_DEG, (median_of_medians, p90)
    assert p90 <= measured_p90 + MARGIN_DEG, (median_of_medians, p90)
