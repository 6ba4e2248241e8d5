"""Leave one environment map out over `ar_truth.py` reports of one setting's values.

    python benchmarks/ar_folds.py LABEL=REPORT.json [LABEL=REPORT.json ...]
        [--data DIR ...] [--regions virtual affected shadow] [--light estimated]

Each report is `ar_truth.py` run over the same AR pairs with one value of a setting (the
label names it, e.g. `0.48=/tmp/rho0.48/report.json`). A pair's map is its frame's
`env_map` in the sequence's lighting_gt.json, found under --data (default: the corpus
cache and ../shared/data/synthetic). Per value and map: the median PSNR (dB) over that
map's pairs in the region, under the light asked for. Then `arlight.folds`: for each map
in turn, the value with the best median over the OTHER maps is chosen and scored on the
held-out map. Prints, per region, every value's median over maps, the held-out median and
the values the folds chose; exit 2 on reports that cannot be read or do not match.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from arlight.folds import FoldsError, leave_one_map_out

DEFAULT_DATA = [
    Path.home() / ".cache" / "arlight" / "corpus",
    Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic",
]


def _labelled(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"expected LABEL=REPORT.json, got {text!r}")
    return label, Path(path)


def truth_frames(sequence: str, data: list[Path]) -> list[dict]:
    """The frames of a sequence's lighting_gt.json, from the first --data folder holding it;
    ValueError naming --data when none does."""
    for root in data:
        truth = root / sequence / "lighting_gt.json"
        if truth.is_file():
            return json.loads(truth.read_text())["frames"]
    raise ValueError(f"{sequence}: no lighting_gt.json under {', '.join(map(str, data))} (--data)")


def env_maps(sequence: str, data: list[Path]) -> list[str]:
    """The env_map of every frame of a sequence (`truth_frames`)."""
    return [str(f.get("env_map")) for f in truth_frames(sequence, data)]


def per_map_psnr(rows: list[dict], column: str, maps_of: dict[str, list[str]]) -> dict[str, float]:
    """{map: median over its pairs of rows' `column`}."""
    values: dict[str, list[float]] = defaultdict(list)
    for row in rows:
        value = row.get(column)
        if value is not None and np.isfinite(value):
            values[maps_of[row["sequence"]][row["frame"]]].append(float(value))
    return {m: float(np.median(v)) for m, v in values.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=_labelled, help="LABEL=report.json")
    parser.add_argument("--data", nargs="+", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--regions", nargs="+", default=["virtual", "affected", "shadow"])
    parser.add_argument("--light", default="estimated", help="estimated or gt_light")
    args = parser.parse_args(argv)
    try:
        reports = {}
        for label, path in args.reports:
            reports[label] = json.loads(path.read_text())["rows"]
        sequences = {r["sequence"] for rows in reports.values() for r in rows}
        maps_of = {s: env_maps(s, args.data) for s in sorted(sequences)}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"ar_folds: {exc}", file=sys.stderr)
        return 2
    pairs = Counter(maps_of[r["sequence"]][r["frame"]] for r in next(iter(reports.values())))
    print(f"{sum(pairs.values())} pairs, {len(pairs)} maps; PSNR dB ({args.light}), medians")
    for region in args.regions:
        column = f"{args.light}_psnr_{region}"
        psnr = {label: per_map_psnr(rows, column, maps_of) for label, rows in reports.items()}
        try:  # the folds minimise: a loss of -PSNR
            folds = leave_one_map_out({k: {m: -v for m, v in d.items()} for k, d in psnr.items()})
        except FoldsError as exc:
            print(f"ar_folds: {region}: {exc}", file=sys.stderr)
            return 2
        fixed = "  ".join(f"{k} {-v:.2f}" for k, v in folds.fixed_median.items())
        print(
            f"{region:9s} median over maps: {fixed} | held out {-folds.held_out_median:.2f} "
            f"(chosen: {folds.choices_text()})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
