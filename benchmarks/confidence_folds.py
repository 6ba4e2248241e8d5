"""The confidence's conditioning factor chosen leaving maps out (decision 0065).

    python benchmarks/confidence_folds.py record SEQ [SEQ ...] --preset fast --out ROWS.jsonl
    python benchmarks/confidence_folds.py folds ROWS.jsonl [ROWS.jsonl ...]

`record` runs the pipeline over sequences with ground truth (as `arlight bench` does, poses
from the data) and writes one row per frame: its map, the upper-hemisphere error of the
reported direction (degrees), the reported confidence, the fit's condition number, the
conditioning factor in that value, whether the direction is a kept compact source's, and
the other factors' inputs (for benchmarks/confidence_factors.py).

`folds` re-scores each frame with other shapes of the conditioning factor,
min(1, (10^c0 / cond)^power) floored at MIN_FACTOR (the other factors as recorded; a
source's confidence has none), and ranks them against the error (Spearman, over all frames
of each ROWS file). Leaving one map out, the shape with the best summed Spearman over the
other maps' frames of every file is picked; the table counts the picks and gives each
file's Spearman with the held-out map's frames scored by their fold's pick.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from arlight import bench, evaluation
from arlight.pipeline.config import Config
from arlight.pipeline.light_confidence import MIN_FACTOR, conditioning_factor
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.runtime import configure_process


def _power(c0: float, power: float):
    return lambda log_cond: np.clip(10.0 ** ((c0 - log_cond) * power), MIN_FACTOR, 1.0)


# the conditioning factor's shapes, of log10(condition number): the one before decision 0065,
# then min(1, (10^c0 / cond)^power)
SHAPES = {"1 / (1 + log10(cond) / 5)": lambda log_cond: 1.0 / (1.0 + log_cond / 5.0)} | {
    f"{c0:g} / {p:g}": _power(c0, p)
    for c0 in (3.0, 3.5)
    for p in (0.0, 0.3, 0.5, 0.8, 1.0, 1.5, 2.0)
}


def record(sequences: list[str], preset: str, out: Path) -> None:
    """One JSON row per frame of each sequence (see the module docstring)."""
    configure_process()
    config = Config.from_preset(preset)
    with out.open("w") as fh:
        for path in sequences:
            seq = bench.open_data([path], None, 0)[0]
            if seq.truth is None:
                raise SystemExit(f"{path}: no lighting_gt.json (record needs ground truth)")
            pipeline = Pipeline(config, seq.camera)
            for i, frame in enumerate(seq.frames):
                result = pipeline.process(frame)
                truth = seq.truth[i]
                c = result.confidence
                row = {
                    "sequence": seq.name,
                    "map": truth.env_map,
                    "error_deg": evaluation.angular_error_deg(
                        result.dominant_direction_camera, truth.dominant_upper_camera
                    ),
                    "confidence": c.value,
                    "condition_number": c.condition_number
                    if math.isfinite(c.condition_number)
                    else None,
                    "conditioning": conditioning_factor(c.condition_number),
                    "from_source": bool(result.compact_sources),
                    # the other factors' inputs (benchmarks/confidence_factors.py)
                    "samples": int(c.samples),
                    "bands": int(c.bands_estimated),
                    "normal_spread": float(c.normal_spread),
                    "horizon_deg": float(c.horizon_disagreement_deg),
                    "side_share": c.side_share,
                    "jump_deg": float(c.jump_deg),
                    "disagreement_deg": float(result.diagnostics.get("fit_disagreement_deg", 0.0)),
                    "edge_step": float(result.diagnostics.get("compact", {}).get("edge_step", 0.0)),
                }
                fh.write(json.dumps(row) + "\n")
            print(f"{seq.name}: {len(seq.frames)} frames", flush=True)


def _rows(path: Path) -> dict[str, np.ndarray]:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line]
    keys = {"map", "error_deg", "confidence", "condition_number", "conditioning", "from_source"}
    if not rows or any(not isinstance(r, dict) or not keys <= r.keys() for r in rows):
        raise ValueError(f"{path}: not rows written by `record` (each needs {sorted(keys)})")
    rows = [r for r in rows if r["confidence"] > 0 and r["condition_number"] is not None]
    return {
        "map": np.array([r["map"] for r in rows]),
        "error": np.array([r["error_deg"] for r in rows]),
        # the confidence without its conditioning factor (a source's has none)
        "rest": np.array(
            [r["confidence"] / (1.0 if r["from_source"] else r["conditioning"]) for r in rows]
        ),
        "log_cond": np.log10([max(r["condition_number"], 1.0) for r in rows]),
        "source": np.array([r["from_source"] for r in rows]),
    }


def _scored(rows: dict[str, np.ndarray], shape: str) -> np.ndarray:
    """Each frame's confidence with the conditioning factor of `shape` (a SHAPES key)."""
    factor = SHAPES[shape](rows["log_cond"])
    return rows["rest"] * np.where(rows["source"], 1.0, factor)


def _spearman(score: np.ndarray, error: np.ndarray) -> float:
    return float(spearmanr(score, error).statistic)


def folds(files: list[Path]) -> None:
    """The leave-one-map-out table (see the module docstring)."""
    sets = {f.name: _rows(f) for f in files}
    maps = sorted(set.intersection(*(set(r["map"]) for r in sets.values())))
    print("| conditioning factor (c0 / power) | " + " | ".join(sets) + " |")
    print("|---" * (len(sets) + 1) + "|")
    for shape in SHAPES:
        cells = [f"{_spearman(_scored(r, shape), r['error']):+.3f}" for r in sets.values()]
        print(f"| {shape} | " + " | ".join(cells) + " |")
    picks: collections.Counter = collections.Counter()
    held = {name: np.zeros(len(r["error"])) for name, r in sets.items()}
    for m in maps:

        def training(shape: str, m: str = m) -> float:
            return sum(
                _spearman(_scored(r, shape)[r["map"] != m], r["error"][r["map"] != m])
                for r in sets.values()
            )

        best = min(SHAPES, key=training)
        picks[best] += 1
        for name, r in sets.items():
            held[name][r["map"] == m] = _scored(r, best)[r["map"] == m]
    print(
        f"\nleft out one at a time ({len(maps)} maps), picks: "
        + ", ".join(f"{k} x{v}" for k, v in picks.most_common())
    )
    for name, r in sets.items():
        print(f"{name}: held-out Spearman {_spearman(held[name], r['error']):+.3f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="per-frame rows of sequences with ground truth")
    rec.add_argument("sequences", nargs="+", help="sequence folders with lighting_gt.json")
    rec.add_argument("--preset", default="fast", choices=["full", "fast", "mobile"])
    rec.add_argument("--out", type=Path, required=True, help="rows, one JSON object a line")
    fold = sub.add_parser("folds", help="the conditioning factor's shapes, leaving maps out")
    fold.add_argument("rows", nargs="+", type=Path, help="files written by `record`")
    args = parser.parse_args(argv)
    try:
        if args.command == "record":
            record(args.sequences, args.preset, args.out)
        else:
            folds(args.rows)
    except (OSError, ValueError, KeyError, bench.BenchError) as exc:
        print(f"confidence_folds.py {args.command}: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
