"""Leave-one-map-out choice of how the compact source is used, from light replays.

    python benchmarks/light_replay.py replay CACHE --compact min_gain=0.005 \
        --truth-dir CORPUS --json REPLAY.json
    python benchmarks/compact_folds.py REPLAY.json [MORE.json ...] [--table]

The replay keeps, per frame, the SH-only error, the error with the source found at the
lowest threshold (its gain, its estimated share, how much of its shadow edge's step the image
shows) and the source's own direction's error. A policy uses the source only where its gain
and its edge reach thresholds; the thresholds are chosen on every map but one (lowest median
over those maps of the per-map median error) and judged on the one left out. Several reports
are pooled (a map in two of them is one map). Printed: how well each statistic tells the
frames the source helps from those it hurts (AUC), then per policy the median over maps of
the held-out errors, the p90 over frames and the worst map, beside the SH alone.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys

import numpy as np

GAINS = (0.005, 0.01, 0.02, 0.03, 0.05, 0.08, 0.12, 0.2, 1e9)
EDGES = (0.0, 0.03, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4)  # ln steps across the shadow edge
POLICIES = {
    "gain": [(g, 0.0) for g in GAINS],
    "gain+edge": list(itertools.product(GAINS, EDGES)),
}


def _errors(rows: list[dict], gain: float, edge: float) -> np.ndarray:
    """Per frame: the source's direction where it is kept at these thresholds, else the SH's."""
    out = []
    for r in rows:
        use = (
            r.get("gain") is not None
            and r["gain"] >= gain
            and (edge <= 0.0 or (r.get("edge") or 0.0) >= edge)
        )
        out.append(r["source_or_sh"] if use else r["sh_only"])
    return np.asarray(out)


def _per_map(rows: list[dict], errors: np.ndarray) -> dict[str, float]:
    by_map: dict[str, list[float]] = {}
    for r, e in zip(rows, errors, strict=True):
        by_map.setdefault(r["map"], []).append(float(e))
    return {m: float(np.median(v)) for m, v in by_map.items()}


def held_out(
    rows: list[dict], choices: list[tuple[float, float]], criterion: str = "median"
) -> tuple[dict[str, float], list[float], dict]:
    """(per held-out map: its median error, every held-out frame's error, chosen thresholds);
    the thresholds minimise the `criterion` ("median" or "mean") over the training maps of
    their median errors (the mean moves less when one map's median jumps)."""
    pool = np.median if criterion == "median" else np.mean
    maps = sorted({r["map"] for r in rows})
    per_map, frames, chosen = {}, [], {}
    for m in maps:
        train = [r for r in rows if r["map"] != m]
        test = [r for r in rows if r["map"] == m]
        best = min(
            choices,
            key=lambda c: pool(list(_per_map(train, _errors(train, *c)).values())),
        )
        e = _errors(test, *best)
        per_map[m] = float(np.median(e))
        frames += e.tolist()
        chosen[m] = best
    return per_map, frames, chosen


def auc(scores: np.ndarray, good: np.ndarray) -> float:
    """The chance that a frame the source helps scores above one it hurts (ties half)."""
    pos, neg = scores[good], scores[~good]
    if not len(pos) or not len(neg):
        return float("nan")
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def _load(paths: list[str], parser: argparse.ArgumentParser) -> list[dict]:
    rows: list[dict] = []
    for path in paths:
        try:
            rows += json.loads(open(path).read())["rows"]
        except (OSError, ValueError, KeyError) as exc:
            parser.error(f"REPLAY {path}: not a light_replay --json report ({exc})")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("replay", nargs="+", help="light_replay --json reports made with --compact")
    parser.add_argument("--table", action="store_true", help="also print the per-map table")
    parser.add_argument(
        "--criterion",
        choices=("median", "mean"),
        default="median",
        help="what the thresholds minimise over the training maps' median errors",
    )
    args = parser.parse_args(argv)
    rows = _load(args.replay, parser)
    sh_only = _per_map(rows, np.asarray([r["sh_only"] for r in rows]))
    print(
        f"SH only: median over maps {np.median(list(sh_only.values())):.1f}, mean "
        f"{np.mean(list(sh_only.values())):.1f}, p90 frames "
        f"{np.percentile([r['sh_only'] for r in rows], 90):.1f}, worst map "
        f"{max(sh_only.values()):.1f} ({len(sh_only)} maps, {len(rows)} frames)"
    )
    found = [r for r in rows if r.get("gain") is not None]
    good = np.asarray([r["source_or_sh"] < r["sh_only"] for r in found])
    print(f"frames with a source found: {len(found)}, helped {int(good.sum())}")
    for key in ("gain", "edge", "share", "contrast"):
        values = np.asarray([r.get(key) if r.get(key) is not None else np.nan for r in found])
        if np.isfinite(values).any():
            print(f"  AUC helped vs hurt by {key}: {auc(np.nan_to_num(values), good):.2f}")
    for name, choices in POLICIES.items():
        per_map, frames, chosen = held_out(rows, choices, args.criterion)
        print(
            f"{name:9s} held out: median over maps {np.median(list(per_map.values())):.1f}, "
            f"mean {np.mean(list(per_map.values())):.1f}, p90 frames "
            f"{np.percentile(frames, 90):.1f}, worst map {max(per_map.values()):.1f}; "
            f"thresholds chosen {sorted(set(chosen.values()))}"
        )
        if args.table:
            print(f"\n| map | frames | SH only | held out ({name}) | gain, edge chosen |")
            print("|---|---|---|---|---|")
            for m in sorted(per_map, key=lambda k: sh_only[k]):
                n = sum(r["map"] == m for r in rows)
                print(f"| {m} | {n} | {sh_only[m]:.1f} | {per_map[m]:.1f} | {chosen[m]} |")
            print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
