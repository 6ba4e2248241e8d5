"""benchmarks/view_gate.py: the source's direction only in views that face the SH's."""

import json

import numpy as np
import pytest

from benchmarks.view_gate import gated_errors, main

UP = [0.0, 1.0, 0.0]


def _row(sequence, estimate, forward, env_map="m"):
    return {
        "sequence": sequence,
        "frame": 0,
        "env_map": env_map,
        "estimate_world": estimate,
        "forward_world": forward,
    }


def test_the_gate_takes_the_source_only_where_the_sh_faces_the_view():
    # the SH points along +z (azimuth 0): frame a looks along +z (facing), b along +x (90)
    sh = [_row("a", [0.0, 0.6, 0.8], [0.0, 0.0, 1.0]), _row("b", [0.0, 0.6, 0.8], [1.0, 0, 0])]
    source = [_row("a", UP, [0.0, 0.0, 1.0]), _row("b", UP, [1.0, 0.0, 0.0])]
    truth = {("a", 0): UP, ("b", 0): UP}
    sh_error = float(np.degrees(np.arccos(0.6)))
    gated = gated_errors(sh, source, truth, 45.0)["m"]
    assert gated == pytest.approx([0.0, sh_error])  # a: the source; b: the SH
    assert gated_errors(sh, source, truth, 0.0)["m"] == pytest.approx([sh_error, sh_error])
    assert gated_errors(sh, source, truth, 181.0)["m"] == pytest.approx([0.0, 0.0])


def test_a_sequence_without_truth_names_the_data_flag(tmp_path, capsys):
    rows = [_row("nowhere", UP, [0.0, 0.0, 1.0])]
    for name in ("sh", "src"):
        (tmp_path / f"{name}.json").write_text(json.dumps(rows))
    code = main([str(tmp_path / "sh.json"), str(tmp_path / "src.json"), "--data", str(tmp_path)])
    assert code == 2 and "nowhere" in capsys.readouterr().err
