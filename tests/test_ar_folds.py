"""benchmarks/ar_folds.py: a setting's values chosen leaving one environment map out."""

import json

import pytest

from benchmarks.ar_folds import main

MAPS = ("a_1k", "b_1k", "c_1k")


def _data(tmp_path):
    """Three sequences, each lit by one map (two frames)."""
    root = tmp_path / "data"
    for i, name in enumerate(MAPS):
        folder = root / f"s{i}"
        folder.mkdir(parents=True)
        frames = [{"env_map": name}, {"env_map": name}]
        (folder / "lighting_gt.json").write_text(json.dumps({"frames": frames}))
    return root


def _report(tmp_path, label, psnr_of_map):
    rows = [
        {"sequence": f"s{i}", "frame": 1, "estimated_psnr_virtual": psnr_of_map[i]}
        for i in range(len(MAPS))
    ]
    path = tmp_path / f"{label}.json"
    path.write_text(json.dumps({"rows": rows}))
    return f"{label}={path}"


def test_each_held_out_map_gets_the_value_best_on_the_others(tmp_path, capsys):
    # "low" is better on maps a and b, "high" on c (by far)
    low = _report(tmp_path, "low", [22.0, 21.0, 10.0])
    high = _report(tmp_path, "high", [20.0, 20.0, 30.0])
    code = main([low, high, "--data", str(_data(tmp_path)), "--regions", "virtual"])
    out = capsys.readouterr().out
    assert code == 0
    assert "3 pairs, 3 maps" in out
    assert "low 21.00  high 20.00" in out  # medians over the maps
    # a held out: on {b, c} low 15.5, high 25 -> high, 20 on a; b held out: on {a, c} low
    # 16, high 25 -> high, 20 on b; c held out: on {a, b} low 21.5, high 20 -> low, 10 on c
    assert "held out 20.00" in out and "high x2" in out and "low x1" in out


def test_an_unknown_sequence_names_the_data_flag(tmp_path, capsys):
    report = _report(tmp_path, "x", [1.0, 2.0, 3.0])
    code = main([report, "--data", str(tmp_path / "nowhere")])
    assert code == 2 and "--data" in capsys.readouterr().err


def test_a_label_without_a_report_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["only-a-label"])
    assert exit_info.value.code == 2 and "LABEL=REPORT.json" in capsys.readouterr().err
