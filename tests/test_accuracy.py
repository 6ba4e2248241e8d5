"""Accuracy against ground truth on ../shared/data/synthetic, pinned so it cannot regress.

Runs the `full` preset over every frame with the ground-truth poses and checks the median
angular error of dominant_direction_camera. Thresholds are the values measured with
`benchmarks/accuracy.py` (see the issue note) plus a small margin; they are NOT the targets
of the issue (12 degrees), which some sequences do not reach yet.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

from arlight.pipeline.config import Config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from accuracy import DATA, evaluate_sequence  # noqa: E402

# measured median (degrees) + margin
PINNED_MEDIAN_DEG = {
    "dev_a_static_venice": 30.6 + 5.0,
    "dev_b_dynamic_potsdamer": 8.8 + 5.0,
    "dev_c_lightswitch_forest_kiara": 14.1 + 5.0,
    "dev_d_indoor_warehouse": 6.9 + 5.0,
}

pytestmark = pytest.mark.skipif(not DATA.is_dir(),
                                reason=f"ground-truth data not found at {DATA}")


@pytest.mark.parametrize("sequence", sorted(PINNED_MEDIAN_DEG))
def test_full_preset_median_angular_error(sequence):
    errors = evaluate_sequence(DATA / sequence, Config.from_preset("full"))
    assert np.all(np.isfinite(errors))
    assert np.median(errors) <= PINNED_MEDIAN_DEG[sequence]
