"""How steady a light estimate is over a sequence with static lights (no ground truth needed).

Reads the results.jsonl that `arlight estimate ... --out FILE` writes and prints, for
`dominant_direction_world`:

* the median frame-to-frame change (degrees), and
* the median angle between each frame's direction and the sequence's mean direction.

Frames without an estimate (zero direction or confidence 0) are left out and counted.

    .venv/bin/python benchmarks/steadiness.py results.jsonl [--skip N] [--gravity FILE]

With --gravity (a world-frame gravity vector, e.g. 7-Scenes' gravity-direction.txt) it also
prints the angle between the mean direction and "up" (ceiling lights should be near it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between rows of a and b (unit vectors)."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def steadiness(directions: np.ndarray) -> dict[str, float]:
    """directions: (N, 3) unit vectors, world frame, in frame order."""
    if len(directions) < 2:
        raise ValueError(f"need at least 2 estimates, got {len(directions)}")
    step = angles_deg(directions[1:], directions[:-1])
    mean = directions.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-12)
    spread = angles_deg(directions, mean[None, :])
    return {
        "frames": int(len(directions)),
        "median_frame_to_frame_deg": float(np.median(step)),
        "p90_frame_to_frame_deg": float(np.percentile(step, 90)),
        "median_to_mean_deg": float(np.median(spread)),
        "p90_to_mean_deg": float(np.percentile(spread, 90)),
        "mean_direction_world": [round(float(x), 4) for x in mean],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results.jsonl from arlight estimate --out")
    parser.add_argument(
        "--skip",
        type=int,
        default=0,
        help="leave out the first N frames (the temporal filter's warm-up)",
    )
    parser.add_argument(
        "--gravity", type=Path, help="file with the world-frame gravity vector (3 numbers)"
    )
    args = parser.parse_args(argv)
    dirs, missing = [], 0
    for line in args.results.read_text().splitlines()[args.skip :]:
        record = json.loads(line)
        d = np.asarray(record["dominant_direction_world"], dtype=float)
        if record["confidence"]["value"] <= 0 or not np.all(np.isfinite(d)) or not np.any(d):
            missing += 1
            continue
        dirs.append(d / np.linalg.norm(d))
    try:
        stats = steadiness(np.array(dirs))
    except ValueError as exc:
        print(f"steadiness: {exc}", file=sys.stderr)
        return 2
    stats["frames_without_estimate"] = missing
    if args.gravity:
        up = -np.loadtxt(args.gravity).reshape(3)
        up /= np.linalg.norm(up)
        mean = np.asarray(stats["mean_direction_world"])
        stats["mean_to_up_deg"] = float(angles_deg(mean / np.linalg.norm(mean), up))
    for key, value in stats.items():
        print(f"{key:28s} {value if not isinstance(value, float) else round(value, 2)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
