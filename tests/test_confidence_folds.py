"""benchmarks/confidence_folds.py: the conditioning factor's shape chosen leaving maps out."""

import json

import numpy as np

from arlight.pipeline.light_confidence import conditioning_factor
from benchmarks.confidence_folds import main


def _rows(tmp_path, name, seed):
    """Six maps' frames whose error grows with log10(cond) (and noise), their confidence the
    product of a random rest and today's conditioning factor."""
    rng = np.random.default_rng(seed)
    rows = []
    for m in range(6):
        for _ in range(20):
            log_cond = rng.uniform(3.2, 5.0)
            rest = rng.uniform(0.2, 1.0)
            factor = conditioning_factor(10.0**log_cond)
            rows.append(
                {
                    "sequence": f"s{m}",
                    "map": f"map{m}",
                    "error_deg": 10.0 * (log_cond - 3.0) + rng.normal(0.0, 2.0),
                    "confidence": rest * factor,
                    "condition_number": 10.0**log_cond,
                    "conditioning": factor,
                    "from_source": False,
                }
            )
    path = tmp_path / name
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    return path


def test_a_steep_factor_is_picked_where_the_error_follows_the_conditioning(tmp_path, capsys):
    fast, full = _rows(tmp_path, "fast.jsonl", 0), _rows(tmp_path, "full.jsonl", 1)
    assert main(["folds", str(fast), str(full)]) == 0
    out = capsys.readouterr().out
    table = {
        line.split("|")[1].strip(): [float(c) for c in line.split("|")[2:4]]
        for line in out.splitlines()
        if line.startswith("| ") and "conditioning factor" not in line
    }
    # the old, nearly flat factor ranks the frames worse than a steep one, on both files
    old, steep = table["1 / (1 + log10(cond) / 5)"], table["3 / 2"]
    assert old[0] > steep[0] and old[1] > steep[1]
    assert "left out one at a time (6 maps)" in out
    assert "1 / (1 + log10(cond) / 5)" not in out.split("picks:")[1].splitlines()[0]
    assert "fast.jsonl: held-out Spearman -0." in out


def test_a_file_that_is_not_rows_is_refused(tmp_path, capsys):
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"map": "a"}\n')
    assert main(["folds", str(bad)]) == 2
    assert "not rows written by `record`" in capsys.readouterr().err
    assert main(["folds", str(tmp_path / "missing.jsonl")]) == 2
