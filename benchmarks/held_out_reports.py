"""Leave one map out between code versions: the held-out choice over `arlight bench` reports.

`arlight bench --folds` chooses among the configurations of one run. A change of code (not
of a `--set` key) is measured by two runs, one per version; this reads their report.json
files (one configuration each, the same sequences) and, for each environment map, chooses
the version with the lower median over the OTHER maps and takes its error on the held-out
map. It prints each version's median and mean over maps, the median over held-out maps,
how often each version was chosen, and the per-map change of the second against the first.

    .venv/bin/python benchmarks/held_out_reports.py BEFORE/report.json AFTER/report.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def map_medians(path: Path) -> dict[str, float]:
    """{environment map: median error (degrees)} of the report's only configuration.
    ValueError names the file when it is not such a report."""
    try:
        configs = json.loads(path.read_text())["configs"]
        if len(configs) != 1:
            raise ValueError(f"{len(configs)} configurations; give reports of one each")
        config = next(iter(configs.values()))
        maps = config["accuracy"]["by_map"]["maps"]
        return {m: float(v["median"]) for m, v in maps.items()}
    except (OSError, KeyError, TypeError, ValueError) as e:
        raise ValueError(
            f"{path}: not an `arlight bench --out DIR` report.json of sequences with "
            f"ground truth ({type(e).__name__}: {e})"
        ) from None


def held_out(
    variants: list[dict[str, float]], criterion: str = "median"
) -> tuple[list[float], list[int]]:
    """For each map (sorted), the index of the variant with the lowest median (or mean:
    `criterion`) over the OTHER maps, and that variant's error on the map: (held-out
    errors, chosen indices)."""

    def summary(values: list[float]) -> float:
        return float(np.median(values) if criterion == "median" else np.mean(values))

    names = sorted(variants[0])
    held, chosen = [], []
    for m in names:
        others = [summary([v[k] for k in names if k != m]) for v in variants]
        best = int(np.argmin(others))
        chosen.append(best)
        held.append(variants[best][m])
    return held, chosen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path, help="report.json files, oldest first")
    args = parser.parse_args(argv)
    try:
        variants = [map_medians(p) for p in args.reports]
    except ValueError as e:
        parser.error(f"reports: {e}")
    names = sorted(variants[0])
    if any(sorted(v) != names for v in variants):
        parser.error("the reports cover different maps: run them on the same sequences")
    held, chosen = held_out(variants)
    for path, v in zip(args.reports, variants, strict=True):
        values = [v[k] for k in names]
        print(f"{path}: median over maps {np.median(values):.1f}, mean {np.mean(values):.2f}")
    counts = np.bincount(chosen, minlength=len(variants)).tolist()
    print(f"held out: median over {len(names)} maps {np.median(held):.1f}, chosen {counts}")
    if len(variants) == 2:
        change = np.array([variants[1][k] - variants[0][k] for k in names])
        print(
            f"per-map change (second - first): median {np.median(change):+.2f}, mean "
            f"{change.mean():+.2f}; better on {int((change < 0).sum())}, worse on "
            f"{int((change > 0).sum())}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
