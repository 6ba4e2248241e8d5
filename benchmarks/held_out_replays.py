"""Leave one map out over `light_replay.py replay --json` reports, pooled over caches.

Each variant is a group of replay reports (one per cache, e.g. the shared set and the
corpus), named NAME=REPORT[,REPORT...]. Frames are pooled by environment map across the
group's reports, so a map that lights sequences of both sets is held out of both. For each
map, the variant with the lowest median (or mean: --criterion) over the OTHER maps of the
per-map median error is chosen, and its error on the held-out map taken. Printed for the
raw error (before the temporal filter) and the filtered one: each variant's median over
maps, mean over maps and p90 over frames, then the held-out median over maps and how often
each variant was chosen.

    .venv/bin/python benchmarks/held_out_replays.py reg4e-3=SHARED.json,CORPUS.json \\
        reg1e-3=SHARED1.json,CORPUS1.json ...
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run as a script
from benchmarks.held_out_reports import held_out  # noqa: E402


def per_map(paths: list[Path], kind: str) -> tuple[dict[str, float], list[float]]:
    """{map: median error} and every frame's error, pooled over the reports."""
    by_map: dict[str, list[float]] = {}
    frames: list[float] = []
    for path in paths:
        try:
            for row in json.loads(path.read_text())["rows"]:
                by_map.setdefault(row["map"], []).append(float(row[kind]))
                frames.append(float(row[kind]))
        except (OSError, KeyError, TypeError, ValueError) as e:
            raise ValueError(
                f"{path}: not a `light_replay.py replay --json` report ({type(e).__name__}: {e})"
            ) from None
    return {m: float(np.median(v)) for m, v in by_map.items()}, frames


def _variant(text: str) -> tuple[str, list[Path]]:
    name, _, files = text.partition("=")
    if not files:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=REPORT[,REPORT...]")
    return name, [Path(f) for f in files.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variants", nargs="+", type=_variant, help="NAME=REPORT[,REPORT...]")
    parser.add_argument(
        "--criterion",
        choices=("median", "mean"),
        default="median",
        help="what the choice minimises over the other maps (the mean is steadier with few "
        "maps near the median)",
    )
    args = parser.parse_args(argv)
    for kind in ("raw", "filtered"):
        try:
            tables = [(name, *per_map(paths, kind)) for name, paths in args.variants]
        except ValueError as e:
            parser.error(f"variants: {e}")
        maps = sorted(tables[0][1])
        if any(sorted(t[1]) != maps for t in tables):
            parser.error("the variants cover different maps: replay the same caches")
        print(f"{kind} ({len(maps)} maps):")
        for name, medians, frames in tables:
            values = [medians[m] for m in maps]
            print(
                f"  {name:24s} median over maps {np.median(values):5.1f}  mean "
                f"{np.mean(values):5.2f}  p90 frames {np.percentile(frames, 90):5.1f}"
            )
        held, chosen = held_out([t[1] for t in tables], args.criterion)
        counts = {name: chosen.count(i) for i, (name, *_) in enumerate(tables)}
        print(f"  held out: median over maps {np.median(held):.1f}, chosen {counts}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
