"""`arlight demo`: server, capture and display on this machine, the built-in scene end to end."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from arlight.cli.common import PRESETS, figure, image_size, positive_int
from arlight.demo import run_demo


def add_parser(sub) -> None:
    demo = sub.add_parser(
        "demo",
        help="server + capture + display on this machine: the built-in scene end to end",
        description="Start a server, stream the built-in synthetic scene to it over loopback "
        "in lossless mode, run a display client, and write DIR: frames/ "
        "(composites), results.jsonl and summary.json (fps, latency, per-stage "
        "timings, light direction error).",
    )
    demo.add_argument("--out", default="out", metavar="DIR", help="output folder (default out)")
    demo.add_argument(
        "--frames", type=positive_int, default=24, help="frames of the synthetic scene (default 24)"
    )
    demo.add_argument(
        "--size",
        type=image_size,
        default=(320, 240),
        metavar="WxH",
        help="image size (default 320x240)",
    )
    demo.add_argument(
        "--preset", choices=PRESETS, default="fast", help="pipeline preset (default fast)"
    )
    demo.add_argument("--video", metavar="FILE.mp4", help="also write the composites as a video")
    demo.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    try:
        summary = run_demo(
            out_dir=args.out,
            frames=args.frames,
            size=args.size,
            preset=args.preset,
            video=args.video,
        )
    except RuntimeError as exc:  # StreamError, DisplayError: the loopback service failed
        print(f"arlight demo: error: {exc}", file=sys.stderr)
        return 1
    lat = summary["latency_ms"]
    err = summary["angular_error_deg"]
    sh_err = summary["sh_direction_error_deg"]
    sh_text = (
        f"; the SH's own direction {figure(sh_err['median'], '.1f')} deg"
        if sh_err["median"] is not None
        else ""
    )
    sun = summary["compact_source_to_sun_deg"]
    sun_text = (
        f"; a compact source on {sun['frames']} of {summary['results']} frames, median "
        f"{figure(sun['median'], '.1f')} deg from the scene's sun"
        if sun["frames"]
        else ""
    )
    rho = summary["confidence_vs_error_spearman"]
    rho_text = (
        "; the confidence against the error (Spearman): "
        + ", ".join(
            f"{figure(value, '+.2f')} ({name})"
            for name, value in (
                ("first moment", rho["first_moment"]),
                ("the source against the sun", rho["source_to_sun"]),
            )
            if value is not None
        )
        if any(v is not None for v in rho.values())
        else ""
    )
    stages = ", ".join(f"{k} {v:.0f}" for k, v in summary["timings_ms_median"].items())
    print(
        f"arlight demo: {summary['results']}/{summary['frames_sent']} results, "
        f"{figure(summary['fps'], '.1f')} fps delivered (pipeline alone "
        f"{figure(summary['pipeline_ms_median'], '.0f')} ms/frame = "
        f"{figure(summary['pipeline_fps'], '.1f')} fps); end-to-end latency median "
        f"{figure(lat['median'], '.0f')} ms (p95 {figure(lat['p95'], '.0f')}, lossless: "
        f"includes queueing); median stage ms: {stages}; dominant light error median "
        f"{figure(err['median'], '.1f')} deg (against the first moment of the light above "
        f"the horizon{sh_text}){sun_text}{rho_text}",
        file=sys.stderr,
    )
    plot = Path(args.out) / "latency.png"
    print(
        f"wrote {args.out}/frames/ ({summary['composites']} composites), "
        f"{args.out}/results.jsonl, {args.out}/summary.json"
        + (f", {plot} (latency and fps over time)" if plot.exists() else "")
        + " in "
        f"{time.perf_counter() - t0:.0f} s",
        file=sys.stderr,
    )
    complete = summary["results"] == summary["frames_sent"] == args.frames
    if not complete:
        print("arlight demo: error: not every frame came back", file=sys.stderr)
    return 0 if complete else 1
