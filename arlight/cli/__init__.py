"""The `arlight` command: parse -> frozen Config -> library call; typed errors -> exit codes.

Exit codes: 0 success, 1 unexpected failure, 2 bad input or usage (the message says what to
do).

One module per command, each `add_parser(sub)` (its flags and help) and `run(args)` (a few
lines over library calls): estimate, bench, batch, ibl, serve, stream, record, display,
demo, keys; `synth` is `arlight.synth.command`. `common` holds the usage error, the argument
types and the options several commands share; `client_options` those of the clients
(stream, record, display).

Imports sit at the top of each module, except what only running one command needs and is
costly to load (the pipeline's compute, the clients, the sources, Ray, tqdm, the benchmark
and its plots): that is imported inside the command's `run`, so that building the parser
(every `arlight` call, `--help` included) does not load it for that command.
"""

from __future__ import annotations

import os

# numpy's BLAS (OpenBLAS) starts a thread per core for LightEst's small (50000 x 16) products;
# beside numba's and Open3D's pools those threads spin against each other: on 2 busy cores
# LightEst took up to 16 s a frame, against about 0.11 s with one BLAS thread. OpenBLAS reads
# this when numpy loads, so the command sets it here, before its modules import numpy (a
# user's own OPENBLAS_NUM_THREADS wins). A library user chooses for their own process.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import logging
import sys

from arlight import __version__
from arlight.cli import (
    batch,
    bench,
    demo,
    display,
    estimate,
    ibl,
    keys,
    record,
    serve,
    stream,
)
from arlight.cli.client_options import token_of as _token_of  # noqa: F401 - tests/test_security
from arlight.cli.common import EXIT_BAD_INPUT, positive_int

__all__ = ["EXIT_BAD_INPUT", "build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    from arlight.synth.command import add_parser

    parser = argparse.ArgumentParser(
        prog="arlight",
        description="Probeless light estimation from RGB-D: spherical-harmonics lighting per "
        "frame from recorded data sets, recordings, live cameras (Luxonis OAK, "
        "OpenNI2, RealSense) or the built-in scene, in-process (estimate, batch "
        "on Ray) or as a streaming service (serve, stream, display, record, "
        "demo), with virtual objects rendered into the frames under the "
        "estimated light (--scene). Also: lighting from 360-degree video (ibl), "
        "speed/accuracy benchmarks (bench) and path-traced ground-truth "
        "sequences (synth).",
    )
    parser.add_argument("--version", action="version", version=f"arlight {__version__}")
    parser.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        help="log details (warnings about defaults chosen for the data are shown either way)",
    )
    parser.add_argument(
        "--open3d-threads",
        type=positive_int,
        metavar="N",
        help="CPU threads for Open3D (volume, ray cast, tracking); default: "
        "all cores. 1 makes tracked poses reproducible run to run, at the "
        "cost of a slower Surface stage",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    estimate.add_parser(sub)
    bench.add_parser(sub)
    batch.add_parser(sub)
    ibl.add_parser(sub)
    add_parser(sub)  # synth
    serve.add_parser(sub)
    stream.add_parser(sub)
    record.add_parser(sub)
    display.add_parser(sub)
    demo.add_parser(sub)
    keys.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    from arlight.pipeline.pipeline import FrameError
    from arlight.pipeline.runtime import configure_process
    from arlight.sources.errors import DatasetError

    configure_process(args.open3d_threads)  # once per process, before any Pipeline
    try:
        return args.func(args)
    except (DatasetError, FrameError, ValueError, OSError) as exc:  # incl. ProtocolError,
        # RecordingError and BadInput (all ValueError)
        print(f"arlight {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
