"""benchmarks/ar_compare.py: PSNR medians and per-pair differences of ar_truth.py reports."""

import json

import pytest

from benchmarks.ar_compare import COLUMNS, columns, main


def _report(tmp_path, name, offset, frames=(1, 4)):
    rows = [
        {"sequence": "s", "preset": "fast", "frame": f, "rendering_ms": 100.0 + f}
        | {c: 20.0 + f + offset for c in COLUMNS}
        for f in frames
    ]
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"rows": rows, "overrides": {}}))
    return path


def test_paired_differences_against_the_first_report(tmp_path, capsys):
    base, new = _report(tmp_path, "base", 0.0), _report(tmp_path, "new", 0.5)
    assert main([str(base), str(new)]) == 0
    out = capsys.readouterr().out
    assert "2 pairs" in out and "| 22.50 |" in out  # median of 21 and 24
    assert "+0.50 / +0.50" in out


@pytest.mark.parametrize("content", [None, "{}", "[1, 2]"])
def test_a_missing_or_foreign_file_exits_2_naming_it(tmp_path, capsys, content):
    bad = tmp_path / "bad.json"
    if content is not None:
        bad.write_text(content)
    with pytest.raises(SystemExit) as exit_info:
        main([str(_report(tmp_path, "base", 0.0)), str(bad)])
    assert exit_info.value.code == 2 and "bad.json" in capsys.readouterr().err


def test_reports_without_a_common_pair_are_refused(tmp_path, capsys):
    base = _report(tmp_path, "base", 0.0, frames=(1,))
    other = _report(tmp_path, "other", 0.0, frames=(4,))
    with pytest.raises(SystemExit) as exit_info:
        main([str(base), str(other)])
    assert exit_info.value.code == 2 and "no AR pair" in capsys.readouterr().err


def _report_with(tmp_path, name, fields):
    rows = [
        {"sequence": "s", "preset": "fast", "frame": f, "rendering_ms": 100.0} | fields(f)
        for f in (1, 4)
    ]
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"rows": rows, "overrides": {}}))
    return path


def test_other_lights_and_the_pairs_that_moved(tmp_path, capsys):
    """--lights gt_full compares that variant; --changed lists the pairs whose affected
    region moved by more than the given dB under it, and only those."""
    full = columns(["gt_full"])
    base = _report_with(tmp_path, "base", lambda f: {c: 30.0 for c in full})
    new = _report_with(
        tmp_path, "new", lambda f: {c: 30.0 + (2.0 if f == 4 else 0.1) for c in full}
    )
    assert main([str(base), str(new), "--lights", "gt_full", "--changed", "1"]) == 0
    out = capsys.readouterr().out
    assert "gt_full affected" in out and "| 31.05 |" in out
    assert "s fast frame 4: 30.00 -> 32.00" in out and "frame 1:" not in out


def test_a_light_the_report_lacks_exits_2_naming_it(tmp_path, capsys):
    old = _report(tmp_path, "old", 0.0)  # gt_light and estimated only
    with pytest.raises(SystemExit) as exit_info:
        main([str(old), "--lights", "gt_full"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "old.json has no gt_full_psnr_affected" in err
