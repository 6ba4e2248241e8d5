"""`arlight display`: the thin display client of one session."""

from __future__ import annotations

import argparse
import sys

from arlight.cli.client_options import (
    add_foxglove_options,
    add_key_options,
    add_reconnect_timeout,
    client_keys,
    foxglove_address,
    token_of,
    warn_if_exposed,
)
from arlight.cli.common import (
    LAYOUT_NAMES,
    BadInput,
    check_address,
    count,
    engine_layouts,
    positive_float,
    positive_int,
)
from arlight.cli.stop_signals import finalised_on_sigterm


def add_parser(sub) -> None:
    disp = sub.add_parser(
        "display",
        help="subscribe to a session: write its Results and composites, print fps",
        description="The thin display client: receives the Results of one session from the "
        "server, prints frames per second and latency, and writes results.jsonl, "
        "composited frames, a video and latency.png; records the Results to MCAP "
        "(--record), serves them to Foxglove (--foxglove) and to a browser "
        "(--http). Exits when the stream ends.",
    )
    disp.add_argument(
        "--server", required=True, metavar="ADDRESS", help="the server, tcp://HOST:PORT"
    )
    disp.add_argument(
        "--session",
        required=True,
        metavar="NAME",
        help="the session to show (as printed by `arlight stream`)",
    )
    disp.add_argument(
        "--out", metavar="DIR", help="write DIR/results.jsonl and DIR/frames/NNNNNN.png"
    )
    disp.add_argument(
        "--export",
        type=engine_layouts,
        metavar="LAYOUTS",
        help="with --out, also the light in these engines' layouts in each "
        'results.jsonl line ("exports"; camera frame, the engine\'s '
        "axes): comma-separated from " + LAYOUT_NAMES,
    )
    disp.add_argument("--video", metavar="FILE.mp4", help="write the composites as a video")
    disp.add_argument(
        "--video-fps",
        type=positive_float,
        default=15.0,
        metavar="FPS",
        help="frame rate written into the video (default 15)",
    )
    disp.add_argument("--max-results", type=positive_int, metavar="N", help="exit after N results")
    disp.add_argument(
        "--idle-exit",
        type=positive_float,
        metavar="S",
        help="exit after S seconds without a result",
    )
    disp.add_argument(
        "--follow",
        action="store_true",
        help="keep waiting when the stream ends (for the next stream: it must "
        "use the same token, `arlight stream --token-file F`)",
    )
    disp.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record the Results to an MCAP file: as received (/arlight/result) "
        "and in Foxglove's schemas (composite, light, lighting JSON, /tf)",
    )
    add_foxglove_options(disp, "the session's Results (composite, light, lighting, pose)")
    disp.add_argument(
        "--http",
        metavar="[HOST:]PORT",
        help="serve a live page for a browser on this address (HOST default "
        "127.0.0.1; 0.0.0.0:PORT for a tablet on the network)",
    )
    disp.add_argument(
        "--token",
        metavar="T",
        help="the session's token, as `arlight stream` prints it (or the "
        "server's admin token); without it the server refuses",
    )
    disp.add_argument(
        "--token-file",
        metavar="FILE",
        help="read --token from FILE (keeps it out of the process list)",
    )
    add_key_options(disp)
    add_reconnect_timeout(disp)
    disp.set_defaults(func=run)


@finalised_on_sigterm
def run(args: argparse.Namespace) -> int:
    from arlight.client.display import DisplayClient, DisplayError, DisplayOptions, print_line

    check_address(args.server, "--server")
    if args.video and not args.video.lower().endswith((".mp4", ".m4v", ".mov")):
        raise BadInput(f"--video expects an .mp4 file, got {args.video!r}")
    if args.export and not args.out:
        raise BadInput("--export adds to the results.jsonl that --out writes: give --out DIR")
    if args.record and not args.record.lower().endswith(".mcap"):
        raise BadInput(f"--record must name an .mcap file, got {args.record!r}")
    foxglove = foxglove_address(args)
    http = None
    if args.http:
        from arlight.client.web_display import parse_http_address

        try:
            http = parse_http_address(args.http)
        except ValueError as exc:
            raise BadInput(str(exc)) from None
        warn_if_exposed("--http", *http)
    options = DisplayOptions(
        server=args.server,
        session=args.session,
        out_dir=args.out,
        exports=tuple(args.export or ()),
        record=args.record,
        foxglove=foxglove,
        http=http,
        video=args.video,
        video_fps=args.video_fps,
        max_results=args.max_results,
        idle_exit_s=args.idle_exit,
        follow=args.follow,
        reconnect_timeout_s=args.reconnect_timeout,
        token=token_of(args),
        keys=client_keys(args),
    )
    print(
        f"arlight display: session {args.session!r} on {args.server}"
        + (f", writing {args.out}/results.jsonl and {args.out}/frames/" if args.out else "")
        + (f", video {args.video}" if args.video else "")
        + (f", recording {args.record}" if args.record else ""),
        file=sys.stderr,
        flush=True,
    )
    client = DisplayClient(options, printer=print_line)
    try:
        summary = client.run()
    except DisplayError as exc:
        print(f"arlight display: error: {exc}", file=sys.stderr)
        return 1
    info = summary.to_dict()
    lat = info["latency_ms"]
    latency = (
        f"{lat['kind'].replace('_', '-')} latency median {lat['median']:.0f} ms, p95 "
        f"{lat['p95']:.0f} ms"
        if lat["median"] is not None
        else "no latency measured"
    )
    print(
        f"arlight display: {info['results']} results ({info['composites']} composites), "
        f"{info['fps']:.1f} fps, {latency}; {info['results_missed']} missed; "
        f"{'stream ended' if info['stream_ended'] else 'stopped'}",
        file=sys.stderr,
    )
    if client.plot_path is not None:
        print(f"arlight display: latency and fps over time in {client.plot_path}", file=sys.stderr)
    if args.record:
        print(
            f"arlight display: recorded {count(info['results'], 'result')} to "
            f"{args.record} (Foxglove opens it; topics in "
            "docs/guides/foxglove-and-browser.md)",
            file=sys.stderr,
        )
    return 0
