"""benchmarks/confidence_factors.py: the confidence's scales chosen leaving maps out."""

import json

import numpy as np

from benchmarks.confidence_factors import code_scales, load, main, scored


def _rows(tmp_path, name, seed, view_tracks_error: bool):
    """Six maps' frames whose error grows with log10(cond); the share of side-facing normals
    either falls as the error grows (the view factor ranks it) or is noise. The recorded
    confidence is the one the code's scales give."""
    rng = np.random.default_rng(seed)
    rows = []
    for m in range(6):
        for k in range(20):
            log_cond = rng.uniform(3.2, 5.0)
            error = 10.0 * (log_cond - 3.0) + rng.normal(0.0, 2.0)
            side = max(0.0, 0.25 - error / 100.0) if view_tracks_error else rng.uniform(0.0, 0.3)
            rows.append(
                {
                    "sequence": f"s{m}",
                    "map": f"map{m}",
                    "error_deg": error,
                    "confidence": 1.0,  # replaced below
                    "condition_number": 10.0**log_cond,
                    "conditioning": 0.0,
                    "from_source": k == 0,
                    "samples": 8000,
                    "bands": 4,
                    "normal_spread": rng.uniform(0.05, 0.3),
                    "horizon_deg": rng.uniform(0.0, 20.0),
                    "side_share": None if k == 0 else side,
                    "jump_deg": rng.uniform(0.0, 10.0),
                    "disagreement_deg": rng.uniform(0.0, 10.0),
                    "edge_step": rng.uniform(0.0, 1.0),
                }
            )
    path = tmp_path / name
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    recorded = scored(load(path), code_scales())
    for row, value in zip(rows, recorded, strict=True):
        row["confidence"] = float(value)
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    return path


def _table(out: str) -> dict[tuple[str, str], list[float]]:
    return {
        (cells[1].strip(), cells[2].strip().replace(" (code)", "")): [float(c) for c in cells[3:-1]]
        for cells in (line.split("|") for line in out.splitlines())
        if len(cells) > 4 and cells[1].strip() in code_scales()
    }


def test_a_view_factor_that_says_nothing_is_left_out(tmp_path, capsys):
    fast = _rows(tmp_path, "fast.jsonl", 0, view_tracks_error=False)
    full = _rows(tmp_path, "full.jsonl", 1, view_tracks_error=False)
    assert main([str(fast), str(full)]) == 0
    out = capsys.readouterr().out
    table = _table(out)
    off, strong = table[("view", "0")], table[("view", "0.2")]
    assert off[0] < strong[0] and off[1] < strong[1]  # more negative: ranks the error better
    assert "left out one map at a time (6 maps)" in out
    picks = out.split("picks: ")[1].splitlines()[0]
    assert "view 0" in picks and "view 0.2" not in picks
    assert "fast.jsonl: held-out Spearman -0." in out


def test_a_view_factor_that_ranks_the_error_is_kept(tmp_path, capsys):
    fast = _rows(tmp_path, "fast.jsonl", 2, view_tracks_error=True)
    full = _rows(tmp_path, "full.jsonl", 3, view_tracks_error=True)
    assert main([str(fast), str(full)]) == 0
    table = _table(capsys.readouterr().out)
    off, strong = table[("view", "0")], table[("view", "0.2")]
    assert strong[0] < off[0] and strong[1] < off[1]


def test_rows_of_other_code_or_without_the_factors_are_refused(tmp_path, capsys):
    good = _rows(tmp_path, "rows.jsonl", 4, view_tracks_error=False)
    rows = [json.loads(line) for line in good.read_text().splitlines()]
    rows[3]["confidence"] *= 0.5
    stale = tmp_path / "stale.jsonl"
    stale.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert main([str(stale)]) == 2
    assert "record them again" in capsys.readouterr().err
    old = tmp_path / "old.jsonl"  # rows of decision 0065's recorder: no factor inputs
    old.write_text(json.dumps({"map": "a", "error_deg": 1.0, "confidence": 0.5}) + "\n")
    assert main([str(old)]) == 2
    assert "with every factor's input" in capsys.readouterr().err
