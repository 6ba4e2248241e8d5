"""The reported confidence's scales chosen leaving maps out (decision 0066).

    python benchmarks/confidence_folds.py record SEQ [SEQ ...] --preset fast --out ROWS.jsonl
    python benchmarks/confidence_factors.py ROWS_fast.jsonl ROWS_full.jsonl

Each recorded frame's confidence is re-scored with other scales of its factors
(`light_confidence`: the normals' spread at which the "normals" factor reaches 1, the share
of side-facing normals at which the "view" factor does, the steadiness and agreement
factors' degrees, the samples' count; `compact_light.EDGE_STEP_FULL` for a kept source's),
the conditioning factor as in the code. The re-scoring is checked first: with the code's
scales it must give every frame's recorded confidence.

Printed: each scale alone on a grid (Spearman with the error over all frames of each file),
then a joint grid of the normals, view and steadiness scales left out one map at a time
(the candidate with the best summed Spearman over the other maps' frames of every file is
picked; the picks are counted and each file's Spearman given with the held-out map's frames
scored by their fold's pick).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from arlight.pipeline import compact_light as cl
from arlight.pipeline import light_confidence as lc

FIELDS = (
    "map",
    "error_deg",
    "confidence",
    "condition_number",
    "from_source",
    "samples",
    "bands",
    "normal_spread",
    "horizon_deg",
    "side_share",
    "jump_deg",
    "disagreement_deg",
    "edge_step",
)
OFF = float("inf")  # a scale at which its factor is 1 everywhere


def code_scales() -> dict[str, float]:
    """The scales as the code has them."""
    return {
        "samples": float(lc.SAMPLES_FULL),
        "normals": lc.NORMAL_SPREAD_FULL,
        "view": lc.SIDE_SHARE_FULL,
        "steadiness_deg": lc.JUMP_SCALE_DEG,
        "agreement_deg": lc.AGREE_SCALE_DEG,
        "edge_step": cl.EDGE_STEP_FULL,
    }


GRID = {
    "samples": [2000.0, 5000.0, 10000.0],
    "normals": [0.0, 0.05, 0.1, 0.15, 0.3],
    "view": [0.0, 0.05, 0.1, 0.2],
    "steadiness_deg": [10.0, 15.0, 20.0, 40.0, OFF],
    "agreement_deg": [10.0, 20.0, 40.0, OFF],
    "edge_step": [0.25, 0.5, 1.0],
}
JOINT = ("normals", "view", "steadiness_deg")


def load(path: Path) -> dict[str, np.ndarray]:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line]
    if not rows or any(not isinstance(r, dict) or not set(FIELDS) <= r.keys() for r in rows):
        raise ValueError(
            f"{path}: not rows of `confidence_folds.py record` with every factor's input "
            f"(each needs {list(FIELDS)}; record them again)"
        )
    rows = [r for r in rows if r["confidence"] > 0 and r["condition_number"] is not None]

    def column(key: str) -> np.ndarray:
        return np.array([np.nan if r[key] is None else r[key] for r in rows], np.float64)

    out = {key: column(key) for key in FIELDS if key not in ("map", "from_source")}
    out["map"] = np.array([r["map"] for r in rows])
    out["from_source"] = np.array([bool(r["from_source"]) for r in rows])
    return out


def _ramp(x: np.ndarray, full: float) -> np.ndarray:
    """min(1, x / full) floored at MIN_FACTOR; 1 everywhere at a scale of 0 (no factor)."""
    if full <= 0.0:
        return np.ones_like(x)
    return np.clip(x / full, lc.MIN_FACTOR, 1.0)


def _decay(deg: np.ndarray, scale: float) -> np.ndarray:
    return np.maximum(lc.MIN_FACTOR, np.exp(-deg / scale))


def scored(rows: dict[str, np.ndarray], scales: dict[str, float]) -> np.ndarray:
    """Each frame's reported confidence with these scales (light_confidence's factors)."""
    conditioning = np.array([lc.conditioning_factor(c) for c in rows["condition_number"]])
    fit = (
        np.minimum(1.0, rows["samples"] / scales["samples"])
        * conditioning
        * np.where(rows["bands"] >= 2, 1.0, lc.NO_DIRECTION_FACTOR)
        * _ramp(rows["normal_spread"], scales["normals"])
        * np.maximum(lc.MIN_FACTOR, np.exp(-rows["horizon_deg"] / lc.HORIZON_SCALE_DEG))
    )
    side = rows["side_share"]
    view = np.where(np.isnan(side), 1.0, _ramp(np.nan_to_num(side), scales["view"]))
    steady = _decay(rows["jump_deg"], scales["steadiness_deg"])
    agree = _decay(rows["disagreement_deg"], scales["agreement_deg"])
    from_fit = np.clip(fit * view * steady * agree, 0.0, 1.0)
    from_source = np.clip(_ramp(rows["edge_step"], scales["edge_step"]) * steady, 0.0, 1.0)
    return np.where(rows["from_source"], from_source, from_fit)


def _spearman(score: np.ndarray, error: np.ndarray) -> float:
    return float(spearmanr(score, error).statistic)


def _label(scales: dict[str, float], base: dict[str, float]) -> str:
    changed = [f"{k} {v:g}" for k, v in scales.items() if v != base[k]]
    return ", ".join(changed) or "as in the code"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rows", nargs="+", type=Path, help="files written by `record`")
    args = parser.parse_args(argv)
    try:
        sets = {path.name: load(path) for path in args.rows}
    except (OSError, ValueError) as exc:
        print(f"confidence_factors.py: {exc}", file=sys.stderr)
        return 2
    base = code_scales()
    for name, rows in sets.items():
        worst = float(np.max(np.abs(scored(rows, base) - rows["confidence"])))
        if worst > 1e-9:
            print(
                f"confidence_factors.py: {name}: the code's scales give confidences up to "
                f"{worst:.3g} from the recorded ones (rows of other code? record them again)",
                file=sys.stderr,
            )
            return 2
    print("| scale | value | " + " | ".join(sets) + " |")
    print("|---" * (len(sets) + 2) + "|")
    for key, values in GRID.items():
        for value in values:
            scales = dict(base, **{key: value})
            cells = [f"{_spearman(scored(r, scales), r['error_deg']):+.3f}" for r in sets.values()]
            mark = " (code)" if value == base[key] else ""
            print(f"| {key} | {value:g}{mark} | " + " | ".join(cells) + " |")
    candidates = [
        dict(base, **dict(zip(JOINT, combo, strict=True)))
        for combo in np.array(np.meshgrid(*(GRID[k] for k in JOINT))).reshape(len(JOINT), -1).T
    ]
    scores = [{n: scored(r, c) for n, r in sets.items()} for c in candidates]
    maps = sorted(set.intersection(*(set(r["map"]) for r in sets.values())))
    picks: collections.Counter = collections.Counter()
    held = {n: np.zeros(len(r["error_deg"])) for n, r in sets.items()}
    for m in maps:
        training = [
            sum(
                _spearman(s[n][r["map"] != m], r["error_deg"][r["map"] != m])
                for n, r in sets.items()
            )
            for s in scores
        ]
        best = int(np.argmin(training))
        picks[_label(candidates[best], base)] += 1
        for n, r in sets.items():
            held[n][r["map"] == m] = scores[best][n][r["map"] == m]
    print(
        f"\njoint grid of {', '.join(JOINT)}, left out one map at a time ({len(maps)} maps); "
        "picks: " + "; ".join(f"{k} x{v}" for k, v in picks.most_common())
    )
    for n, r in sets.items():
        print(
            f"{n}: held-out Spearman {_spearman(held[n], r['error_deg']):+.3f} "
            f"(the code's scales {_spearman(scored(r, base), r['error_deg']):+.3f})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
