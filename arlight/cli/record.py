"""`arlight record`: a source as a stream into one MCAP file, no server needed."""

from __future__ import annotations

import argparse
import sys
import time

from arlight.cli.client_options import add_source_options, open_stream_source, stream_options
from arlight.cli.common import BadInput, count
from arlight.cli.stop_signals import finalised_on_sigterm


def add_parser(sub) -> None:
    rec = sub.add_parser(
        "record",
        help="record a source as a stream into one MCAP file (no server needed)",
        description="Write the stream `arlight stream SOURCE` would send (session config, "
        "frames as encoded, timestamps) to one MCAP file; `arlight stream "
        "FILE.mcap` replays it bit-exactly.",
    )
    add_source_options(rec)
    rec.add_argument("--out", required=True, metavar="FILE.mcap", help="the MCAP file to write")
    rec.set_defaults(func=run)


@finalised_on_sigterm
def run(args: argparse.Namespace) -> int:
    from arlight.client.recording import record

    if not args.out.lower().endswith(".mcap"):
        raise BadInput(f"--out must name an .mcap file, got {args.out!r}")
    args.server = None
    source = open_stream_source(args)
    options = stream_options(args, source)
    t0 = time.perf_counter()

    def on_frame(seq: int, parts) -> None:
        size = sum(len(memoryview(p)) for p in parts)
        print(f"[{seq + 1:>5}/{source.num_frames or 'live'}] {size / 1024:8.1f} KiB", flush=True)

    n, session = record(source, args.out, options, on_frame=on_frame)
    print(
        f"arlight record: wrote {count(n, 'frame')} (session {session}, "
        f"{options.mode}, colour {options.color_codec}, depth {options.depth_codec}) to "
        f"{args.out} in {time.perf_counter() - t0:.1f} s; replay with `arlight stream "
        f"{args.out} --server tcp://HOST:PORT`",
        file=sys.stderr,
    )
    return 0
