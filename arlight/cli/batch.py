"""`arlight batch`: many recordings and sequences on Ray, one pipeline per stream."""

from __future__ import annotations

import argparse
import sys

from arlight.batch import BatchOptions, collect_inputs, format_summary, run_batch
from arlight.cli.common import (
    DEPTH_ENCODINGS,
    PRESETS,
    RAY_ADDRESS,
    BadInput,
    config_override,
    count,
    positive_int,
)


def add_parser(sub) -> None:
    batch = sub.add_parser(
        "batch",
        help="estimate the lighting of many recordings / sequences on Ray",
        description="Run the pipeline over many streams on Ray, one actor (and one pipeline "
        "state) per stream: a local Ray, or the cluster at --ray ADDRESS. Each "
        "stream's JSON lines (those `arlight estimate --out` writes) go to "
        "DIR/NAME.jsonl, written whole or not at all; DIR/batch.json lists each "
        "stream as ok, failed (with the reason) or skipped. A rerun skips the "
        "streams already finished. Exit code 1 when any stream failed. Needs "
        "pip install 'arlight[ray]'.",
    )
    batch.add_argument(
        "inputs",
        nargs="*",
        metavar="INPUT",
        help="recordings (FILE.mcap, from `arlight record`), sequence folders "
        "(as `arlight estimate` reads), or folders of recordings",
    )
    batch.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="a running Ray cluster, e.g. ray://HOST:10001 or auto (default: start a local Ray)",
    )
    batch.add_argument(
        "--out", default="batch-out", metavar="DIR", help="results folder (default batch-out)"
    )
    batch.add_argument(
        "--preset",
        choices=PRESETS,
        default="full",
        help="speed/accuracy preset of every stream (default full); also the "
        "CPUs per actor: full 2, fast 1, mobile 1",
    )
    batch.add_argument(
        "--device",
        help="Open3D device of every stream's volume, e.g. CUDA:0 "
        "(then each actor asks Ray for one GPU; default CPU:0)",
    )
    batch.add_argument(
        "--set",
        action="append",
        type=config_override,
        metavar="KEY=VALUE",
        help="override a pipeline Config field for every stream",
    )
    batch.add_argument(
        "--max-frames",
        type=positive_int,
        metavar="N",
        help="only the first N frames of each stream",
    )
    batch.add_argument(
        "--depth-encoding",
        choices=DEPTH_ENCODINGS,
        help="depth encoding of the sequence folders (default: from the layout)",
    )
    batch.add_argument(
        "--force", action="store_true", help="redo streams whose results exist (default: skip them)"
    )
    batch.add_argument("--no-progress", action="store_true", help="no progress bar")
    batch.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Exit 0 when every stream is ok or skipped, 1 when any failed, 2 for bad usage."""
    if args.ray is not None and not RAY_ADDRESS.fullmatch(args.ray):
        raise BadInput(
            f"--ray expects a Ray address such as ray://HOST:10001, HOST:6379 or "
            f"auto, got {args.ray!r}"
        )
    items = collect_inputs(args.inputs)
    options = BatchOptions(
        preset=args.preset,
        overrides=tuple(args.set or ()),
        device=args.device,
        max_frames=args.max_frames,
        depth_encoding=args.depth_encoding,
    )
    print(
        f"arlight batch: {count(len(items), 'stream')}, preset {args.preset}, results in "
        f"{args.out}/",
        file=sys.stderr,
    )
    report = run_batch(
        items,
        args.out,
        options,
        address=args.ray,
        force=args.force,
        progress=sys.stderr.isatty() and not args.no_progress,
    )
    for summary in report.streams:
        print(format_summary(summary))
    print(
        f"arlight batch: {report.count('ok')} ok, {report.count('failed')} failed, "
        f"{report.count('skipped')} skipped; summary in {report.summary_path}",
        file=sys.stderr,
    )
    return 0 if report.ok else 1
