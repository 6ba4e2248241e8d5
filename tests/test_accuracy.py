"""Accuracy against ground truth on ../shared/data/synthetic, pinned so it cannot regress.

Runs the `full` and `fast` presets over every frame with the ground-truth poses and checks
the median angular error of dominant_direction_camera against the medians measured with
`benchmarks/accuracy.py` plus a 3 degree margin, and never above the issue's targets
(12 degrees full, 15 fast).
"""

import sys
from pathlib import Path

import numpy as np
import pytest

from arlight.pipeline.config import Config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from accuracy import DATA, evaluate_sequence  # noqa: E402

MARGIN_DEG = 3.0
TARGET_DEG = {"full": 12.0, "fast": 15.0}
# measured median (degrees), `.venv/bin/python benchmarks/accuracy.py --configs full fast`
MEASURED_MEDIAN_DEG = {
    ("full", "dev_a_static_venice"): 4.2,
    ("full", "dev_b_dynamic_potsdamer"): 7.7,
    ("full", "dev_c_lightswitch_forest_kiara"): 7.0,
    ("full", "dev_d_indoor_warehouse"): 4.3,
    ("full", "dev_e_fewnormals_studio"): 5.2,
    ("fast", "dev_a_static_venice"): 7.3,
    ("fast", "dev_b_dynamic_potsdamer"): 14.2,
    ("fast", "dev_c_lightswitch_forest_kiara"): 8.1,
    ("fast", "dev_d_indoor_warehouse"): 7.0,
    ("fast", "dev_e_fewnormals_studio"): 2.8,
}

pytestmark = [pytest.mark.slow, pytest.mark.data,
              pytest.mark.skipif(not DATA.is_dir(),
                                 reason=f"ground-truth data not found at {DATA}")]


@pytest.mark.parametrize(("preset", "sequence"), sorted(MEASURED_MEDIAN_DEG))
def test_median_angular_error_does_not_regress(preset, sequence):
    errors = evaluate_sequence(DATA / sequence, Config.from_preset(preset))
    assert np.all(np.isfinite(errors))
    limit = min(MEASURED_MEDIAN_DEG[preset, sequence] + MARGIN_DEG, TARGET_DEG[preset])
    assert np.median(errors) <= limit
