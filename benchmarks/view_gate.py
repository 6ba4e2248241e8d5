"""Emulate a view gate for the compact source: its direction only where the SH's faces the view.

    python benchmarks/view_gate.py SH.json SOURCE.json [--data DIR ...]

SH.json and SOURCE.json: `error_by_view.py --json` rows of the same frames, without and with
compact sources (`--set compact_sources=1`). For each threshold T (degrees), a frame reports
the SOURCE run's direction when the SH run's estimate lies within T degrees of azimuth of the
view direction (a back-lit view, where the SH's elevation is least reliable), else the SH
run's. T = 0 is the SH alone, T = 181 the source wherever one was kept. Prints, per T, the
median over maps of each map's median error against the upper-hemisphere truth (found
under --data), the frames' median and p90 and the worst map, then the leave-one-map-out
choice of T (`arlight.folds`). An emulation from two runs: in the pipeline the gate would
also change what the temporal filter carries from frame to frame.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from arlight.folds import leave_one_map_out

try:
    from benchmarks.ar_folds import DEFAULT_DATA, truth_frames
    from benchmarks.error_by_view import azimuth_deg, wrapped
except ModuleNotFoundError:  # run as `python benchmarks/view_gate.py` from the checkout
    from ar_folds import DEFAULT_DATA, truth_frames  # type: ignore[import-not-found,no-redef]
    from error_by_view import azimuth_deg, wrapped  # type: ignore[import-not-found,no-redef]

THRESHOLDS = (0, 30, 45, 60, 90, 135, 181)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def gated_errors(
    sh_rows: list[dict], source_rows: list[dict], truth: dict, threshold_deg: float
) -> dict[str, list[float]]:
    """{map: errors (degrees) of the frames} with the gate at threshold_deg; truth maps
    (sequence, frame) to the upper-hemisphere truth (world)."""
    source = {(r["sequence"], r["frame"]): r for r in source_rows}
    out: dict[str, list[float]] = defaultdict(list)
    for row in sh_rows:
        key = (row["sequence"], row["frame"])
        facing = abs(
            wrapped(azimuth_deg(row["estimate_world"]) - azimuth_deg(row["forward_world"]))
        )
        chosen = source[key] if facing < threshold_deg else row
        out[str(row["env_map"])].append(
            angle_deg(np.asarray(chosen["estimate_world"]), np.asarray(truth[key]))
        )
    return out


def load_truth(rows: list[dict], data: list[Path]) -> dict:
    """(sequence, frame) -> dominant_dir_upper_world of its lighting_gt.json under data."""
    frames = {name: truth_frames(name, data) for name in {row["sequence"] for row in rows}}
    return {
        (row["sequence"], row["frame"]): frames[row["sequence"]][row["frame"]][
            "dominant_dir_upper_world"
        ]
        for row in rows
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sh", type=Path, help="error_by_view.py --json of the SH alone")
    parser.add_argument("source", type=Path, help="the same with compact_sources=1")
    parser.add_argument("--data", nargs="+", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args(argv)
    try:
        sh_rows = json.loads(args.sh.read_text())
        source_rows = json.loads(args.source.read_text())
        truth = load_truth(sh_rows, args.data)
        per_map = {}
        frames = {}
        for t in THRESHOLDS:
            errors = gated_errors(sh_rows, source_rows, truth, t)
            per_map[f"T{t}"] = {m: float(np.median(v)) for m, v in errors.items()}
            frames[f"T{t}"] = np.concatenate([np.asarray(v) for v in errors.values()])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"view_gate: {exc}", file=sys.stderr)
        return 2
    folds = leave_one_map_out(per_map)
    print(f"{len(sh_rows)} frames, {len(folds.maps)} maps; degrees against the upper truth")
    print("| gate T | median over maps | frames: median / p90 | worst map |")
    print("|---|---|---|---|")
    for name, pooled in frames.items():
        print(
            f"| {name} | {folds.fixed_median[name]:.1f} | {np.median(pooled):.1f} / "
            f"{np.percentile(pooled, 90):.1f} | {max(per_map[name].values()):.1f} |"
        )
    print(f"held out by map: {folds.held_out_median:.1f} (chosen: {folds.choices_text()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
