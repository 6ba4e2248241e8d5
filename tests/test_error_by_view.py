"""benchmarks/error_by_view.py: the error's parts and their bins, on hand-made directions."""

import math

import numpy as np
import pytest

from benchmarks.error_by_view import VIEW_BINS, binned, frame_row, main


def _direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def test_a_light_estimated_too_high_in_a_back_lit_view():
    truth = _direction(30.0, 40.0)
    row = frame_row(_direction(30.0, 60.0), truth, forward=_direction(20.0, -20.0))
    assert row["error"] == pytest.approx(20.0)
    assert row["elevation_bias"] == pytest.approx(20.0)
    assert row["azimuth_error"] == pytest.approx(0.0, abs=1e-9)
    assert row["light_from_view"] == pytest.approx(10.0)  # the camera looks towards it
    assert row["true_elevation"] == pytest.approx(40.0)


def test_azimuths_wrap_around():
    row = frame_row(_direction(-170.0, 45.0), _direction(170.0, 45.0), _direction(-175.0, 0.0))
    assert row["azimuth_error"] == pytest.approx(20.0)
    assert row["light_from_view"] == pytest.approx(15.0)


def test_bins_give_the_median_error_and_bias_of_their_frames():
    rows = [
        {"error": e, "elevation_bias": b, "light_from_view": v}
        for e, b, v in ((30.0, 20.0, 10.0), (10.0, 0.0, 30.0), (5.0, -2.0, 170.0))
    ]
    table = binned(rows, "light_from_view", VIEW_BINS)
    assert table[0] == ("0-45", 2, 20.0, 10.0)
    assert table[-1] == ("135-180", 1, 5.0, -2.0)
    assert len(table) == 2  # empty bins are left out


def test_a_folder_without_truth_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path)])
    assert exit_info.value.code == 2 and "lighting_gt.json" in capsys.readouterr().err


def test_an_unknown_key_names_the_flag(tmp_path, capsys):
    (tmp_path / "lighting_gt.json").write_text("{}")
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path), "--set", "no_such_key=1"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--set" in err and "no_such_key" in err
