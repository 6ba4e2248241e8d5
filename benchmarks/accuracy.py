"""Accuracy of the dominant light direction against ground truth (../shared/data/synthetic).

For every sequence: run the Pipeline over its frames with the ground-truth poses and report
the median and 90th percentile of the angular error of dominant_direction_camera against
lighting_gt.json's `dominant_dir_upper_camera` (the light that can reach the scene), for
`full`, `fast` and the no-visibility baseline (K = 1, else `full`), then the aggregates:
median of the per-sequence medians and 90th percentile over all frames.

    .venv/bin/python benchmarks/accuracy.py [--configs full fast baseline] [--max-frames N]
                                            [--json FILE]

`arlight bench ../shared/data/synthetic` reports the same errors (and against the whole
sphere, SH and shading errors, timings); this script stays for the pins in
tests/test_accuracy.py.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from arlight.evaluation import angular_error_deg
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.runtime import configure_process
from arlight.sources.sequence import open_sequence

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic"
CONFIGS = {
    "full": lambda **kw: Config.from_preset("full", **kw),
    "full_nobounce": lambda **kw: Config.from_preset("full", rt_bounce=False, **kw),
    "fast": lambda **kw: Config.from_preset("fast", **kw),
    "baseline": lambda **kw: Config.from_preset("full", visibility=False, **kw),
}


TRUTH_FIELD = "dominant_dir_upper_camera"


def evaluate_sequence(
    folder: Path, config: Config, max_frames: int | None = None, truth_field: str = TRUTH_FIELD
) -> np.ndarray:
    """Per-frame angular errors (degrees) of dominant_direction_camera against `truth_field`."""
    seq = open_sequence(folder, use_poses=True, max_frames=max_frames)
    truth = json.loads((folder / "lighting_gt.json").read_text())["frames"]
    pipeline = Pipeline(config, seq.camera)
    errors = []
    for i, frame in enumerate(seq.frames):
        result = pipeline.process(frame)
        errors.append(angular_error_deg(result.dominant_direction_camera, truth[i][truth_field]))
    return np.array(errors)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--configs", nargs="+", default=["full", "fast", "baseline"], choices=list(CONFIGS)
    )
    parser.add_argument("--sequences", nargs="*", help="names (default: all)")
    parser.add_argument("--max-frames", type=int)
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a Config field for every configuration",
    )
    parser.add_argument("--json", help="write the table as JSON")
    args = parser.parse_args(argv)
    configure_process()
    if not DATA.is_dir():
        print(f"no ground-truth data at {DATA}", file=sys.stderr)
        return 2
    overrides = {}
    for kv in args.set:
        k, _, v = kv.partition("=")
        try:
            overrides[k] = Config.parse_flat_value(k, v)  # as `arlight --set` reads it
        except ValueError as exc:
            parser.error(f"--set {kv}: {exc}")
    seqs = sorted(p for p in DATA.iterdir() if (p / "lighting_gt.json").exists())
    if args.sequences:
        seqs = [p for p in seqs if p.name in args.sequences]
    table = {}
    print(f"{'sequence':34s}" + "".join(f"{c + ' med/p90':>20s}" for c in args.configs))
    for folder in seqs:
        row = {}
        for name in args.configs:
            t0 = time.perf_counter()
            e = evaluate_sequence(folder, CONFIGS[name](**overrides), args.max_frames)
            row[name] = {
                "median_deg": float(np.median(e)),
                "p90_deg": float(np.percentile(e, 90)),
                "per_frame_deg": [round(float(x), 2) for x in e],
                "seconds": time.perf_counter() - t0,
            }
        table[folder.name] = row
        print(
            f"{folder.name:34s}"
            + "".join(
                f"{row[c]['median_deg']:>12.1f} /{row[c]['p90_deg']:>6.1f}" for c in args.configs
            ),
            flush=True,
        )
    for name in args.configs:
        medians = [row[name]["median_deg"] for row in table.values()]
        every = [e for row in table.values() for e in row[name]["per_frame_deg"]]
        print(
            f"{name}: median of the per-sequence medians {np.median(medians):.1f}, "
            f"90th percentile over all frames {np.percentile(every, 90):.1f}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
