"""Leave-one-map-out choice of how the compact source is used, from one light replay.

    python benchmarks/light_replay.py replay CACHE --compact min_gain=0.005 \
        --truth-dir CORPUS --json REPLAY.json
    python benchmarks/compact_folds.py REPLAY.json

The replay keeps, per frame, the SH-only error, the error with the source found at the
lowest threshold (its gain, its estimated share) and the source's own direction's error.
A policy uses the source only where its gain reaches a threshold; the threshold is chosen
on every map but one (lowest median over those maps of the per-map median error) and
judged on the one left out. Printed: per policy, the median over maps of the held-out
errors, the p90 over frames and the worst map, beside the SH alone.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

THRESHOLDS = (0.005, 0.01, 0.02, 0.03, 0.05, 0.08, 0.12, 0.2, 1e9)


def _errors(rows: list[dict], policy: str, threshold: float) -> np.ndarray:
    out = []
    for r in rows:
        use = r.get("gain") is not None and r["gain"] >= threshold
        if not use:
            out.append(r["sh_only"])
        elif policy == "total":
            out.append(r["raw"])
        else:  # "source": the source's direction is reported
            out.append(r["source_or_sh"])
    return np.asarray(out)


def _per_map(rows: list[dict], errors: np.ndarray) -> dict[str, float]:
    by_map: dict[str, list[float]] = {}
    for r, e in zip(rows, errors, strict=True):
        by_map.setdefault(r["map"], []).append(float(e))
    return {m: float(np.median(v)) for m, v in by_map.items()}


def held_out(rows: list[dict], policy: str) -> tuple[dict[str, float], list[float], dict]:
    """(per held-out map: its median error, every held-out frame's error, chosen thresholds)."""
    maps = sorted({r["map"] for r in rows})
    per_map, frames, chosen = {}, [], {}
    for m in maps:
        train = [r for r in rows if r["map"] != m]
        test = [r for r in rows if r["map"] == m]
        best = min(
            THRESHOLDS,
            key=lambda t: np.median(list(_per_map(train, _errors(train, policy, t)).values())),
        )
        e = _errors(test, policy, best)
        per_map[m] = float(np.median(e))
        frames += e.tolist()
        chosen[m] = best
    return per_map, frames, chosen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("replay", help="a light_replay --json report made with --compact")
    parser.add_argument("--table", action="store_true", help="also print the per-map table")
    args = parser.parse_args(argv)
    try:
        rows = json.loads(open(args.replay).read())["rows"]
    except (OSError, ValueError, KeyError) as exc:
        parser.error(f"REPLAY {args.replay}: not a light_replay --json report ({exc})")
    sh_only = _per_map(rows, np.asarray([r["sh_only"] for r in rows]))
    print(
        f"SH only: median over maps {np.median(list(sh_only.values())):.1f}, p90 frames "
        f"{np.percentile([r['sh_only'] for r in rows], 90):.1f}, worst map "
        f"{max(sh_only.values()):.1f} ({len(sh_only)} maps, {len(rows)} frames)"
    )
    for policy in ("total", "source"):
        per_map, frames, chosen = held_out(rows, policy)
        print(
            f"{policy:7s} held out: median over maps {np.median(list(per_map.values())):.1f}, "
            f"p90 frames {np.percentile(frames, 90):.1f}, worst map {max(per_map.values()):.1f}; "
            f"thresholds chosen {sorted(set(chosen.values()))}"
        )
    if args.table:
        per_map, _, chosen = held_out(rows, "source")
        print("\n| map | frames | SH only | held-out source policy | threshold |")
        print("|---|---|---|---|---|")
        for m in sorted(per_map, key=lambda k: sh_only[k]):
            n = sum(r["map"] == m for r in rows)
            print(f"| {m} | {n} | {sh_only[m]:.1f} | {per_map[m]:.1f} | {chosen[m]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
