"""`arlight bench`: speed and accuracy per configuration (report.md, report.json, trade.png)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from arlight.cli.common import (
    BadInput,
    config_override,
    load_scene,
    non_negative_int,
    positive_int,
)


def add_parser(sub) -> None:
    bench = sub.add_parser(
        "bench",
        help="speed and accuracy per configuration: report.md, report.json, trade.png",
        description="Run each configuration (presets, comparators, sweep points) over the same "
        "frames and report per-stage milliseconds (the rows of the paper's table "
        "1, median and spread, warm-up excluded), frames per second and, where the "
        "data has ground truth, the angular error of the dominant light against the "
        "whole sphere and the upper hemisphere, the SH error and the diffuse-shading "
        "error. Poses come from the data (tracking skipped).",
    )
    bench.add_argument(
        "data",
        nargs="*",
        default=["synthetic"],
        metavar="DATA",
        help="'synthetic' (the built-in scene, default), 'synthetic-held' (the "
        "same scene seen by a camera held still, the sun moving half-way: "
        "what a still camera's reuse saves), a sequence folder with "
        "lighting_gt.json, or a folder of them (../shared/data/synthetic)",
    )
    bench.add_argument(
        "--presets",
        nargs="+",
        default=["full", "fast"],
        choices=("full", "fast", "mobile", "baseline", "raycast"),
        help="configurations to compare (default full fast; baseline = full "
        "without visibility, K = 1; raycast = full with object-space "
        "visibility, rays against the volume's mesh, rt_method=raycast)",
    )
    bench.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="a curve: the first preset with KEY set to each value in turn "
        "(any --set key, or size=WxH,... for the built-in scene); repeatable",
    )
    bench.add_argument(
        "--set",
        action="append",
        type=config_override,
        metavar="KEY=VALUE",
        help="override a pipeline Config field for every configuration",
    )
    bench.add_argument(
        "--frames",
        type=positive_int,
        metavar="N",
        help="timed frames of the built-in scene (default 8) / at most N frames "
        "of each sequence (default all)",
    )
    bench.add_argument(
        "--warmup",
        type=non_negative_int,
        default=2,
        metavar="N",
        help="frames per sequence left out of the timings (JIT, caches; default 2)",
    )
    bench.add_argument(
        "--out",
        default="bench-report",
        metavar="DIR",
        help="write DIR/report.json, report.md, trade.png (default bench-report)",
    )
    bench.add_argument("--json", metavar="FILE", help="also write report.json to FILE")
    bench.add_argument(
        "--folds",
        action="store_true",
        help="leave one environment map out: for each map, the configuration "
        "(preset or sweep point) with the lowest median over the OTHER "
        "maps, and its error on the held-out map; shows whether choosing "
        "a configuration generalises to unseen lighting",
    )
    bench.add_argument(
        "--overlap",
        action="store_true",
        help="process each sequence with the next frame's Input..RadTransfer beside this "
        "frame's LightEst, probe and rendering (Pipeline.process_overlapped): FPS is then "
        "the rate results come out ('ms between results'), and 'total' a frame's latency",
    )
    bench.add_argument(
        "--scene",
        metavar="FILE",
        help="render these virtual objects into every frame, so the Rendering "
        "stage is timed: a scene file (docs/scene-files.md) or 'demo' (a "
        "sphere and a torus on the detected ground); poses in each "
        "sequence's pose frame",
    )
    bench.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from arlight.bench import BenchError, parse_sweep, run_benchmark
    from arlight.report import (
        accuracy_table,
        folds_table,
        layout_table,
        map_table,
        speed_table,
        write_report,
    )

    try:
        sweeps = [parse_sweep(text) for text in args.sweep]
        report = run_benchmark(
            args.data,
            args.presets,
            sweeps,
            args.frames,
            args.warmup,
            dict(args.set or []),
            progress=sys.stderr.isatty(),
            scene=load_scene(args),
            folds=args.folds,
            overlap=args.overlap,
        )
    except BenchError as exc:
        raise BadInput(str(exc)) from None
    print(speed_table(report))
    for table in (
        accuracy_table(report),
        map_table(report),
        layout_table(report),
        folds_table(report),
    ):
        if table:
            print()
            print(table)
    written = write_report(report, args.out)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
        written.append(Path(args.json))
    print(f"arlight bench: wrote {', '.join(str(p) for p in written)}", file=sys.stderr)
    return 0
