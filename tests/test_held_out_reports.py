"""benchmarks/held_out_reports.py: the leave-one-map-out choice between two code versions."""

import json

import pytest

from benchmarks.held_out_reports import main


def _report(tmp_path, name, medians):
    maps = {m: {"median": v, "p90": v, "frames": 6} for m, v in medians.items()}
    report = {"configs": {"full": {"accuracy": {"by_map": {"maps": maps}}}}}
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(report))
    return path


def test_each_map_is_judged_by_the_choice_made_without_it(tmp_path, capsys):
    # "after" is 1 degree better on every map but d, where it is 20 worse; the median over
    # any three maps still prefers it, so it is chosen in every fold and d scores its 40
    before = _report(tmp_path, "before", {"a": 10, "b": 12, "c": 14, "d": 20})
    after = _report(tmp_path, "after", {"a": 9, "b": 11, "c": 13, "d": 40})
    assert main([str(before), str(after)]) == 0
    out = capsys.readouterr().out
    assert "held out: median over 4 maps 12.0, chosen [0, 4]" in out
    assert "median -1.00, mean +4.25; better on 3, worse on 1" in out


def test_reports_over_different_maps_are_refused(tmp_path, capsys):
    before = _report(tmp_path, "before", {"a": 10, "b": 12})
    after = _report(tmp_path, "after", {"a": 9, "c": 11})
    with pytest.raises(SystemExit) as exit_info:
        main([str(before), str(after)])
    assert exit_info.value.code == 2 and "different maps" in capsys.readouterr().err


def test_a_missing_or_foreign_file_is_named_without_a_traceback(tmp_path, capsys):
    from benchmarks.held_out_replays import main as replays_main

    foreign = tmp_path / "foreign.json"
    foreign.write_text('{"rows": 3}')
    for run, args in (
        (main, [str(tmp_path / "missing.json")]),
        (main, [str(foreign)]),
        (replays_main, [f"a={foreign}"]),
    ):
        with pytest.raises(SystemExit) as exit_info:
            run(args)
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and "json" in err and "Traceback" not in err


def _replay(tmp_path, name, rows):
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"rows": [{"map": m, "raw": r, "filtered": f} for m, r, f in rows]}))
    return str(path)


def test_replays_pool_a_map_over_both_sets(tmp_path, capsys):
    """A map lighting sequences of both caches is one map: its frames are pooled."""
    from benchmarks.held_out_replays import main as replays_main

    a_shared = _replay(tmp_path, "a1", [("m1", 10, 9), ("m2", 20, 19)])
    a_corpus = _replay(tmp_path, "a2", [("m1", 30, 29), ("m3", 5, 4)])
    b_shared = _replay(tmp_path, "b1", [("m1", 11, 10), ("m2", 21, 20)])
    b_corpus = _replay(tmp_path, "b2", [("m1", 31, 30), ("m3", 6, 5)])
    assert replays_main([f"a={a_shared},{a_corpus}", f"b={b_shared},{b_corpus}"]) == 0
    out = capsys.readouterr().out
    # m1 pools 10 and 30 (median 20): variant a is 20 / 20 / 5 over maps, b 21 / 21 / 6
    assert (
        "raw (3 maps):" in out and "held out: median over maps 20.0, chosen {'a': 3, 'b': 0}" in out
    )
