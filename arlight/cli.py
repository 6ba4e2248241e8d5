"""The `arlight` command: parse -> frozen Config -> library call; typed errors -> exit codes.

Exit codes: 0 success, 1 unexpected failure, 2 bad input or usage (the message says what to do).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
import time

import numpy as np

from arlight import __version__

EXIT_BAD_INPUT = 2


def _parse_override(text: str) -> tuple[str, object]:
    from arlight.pipeline.config import Config

    if "=" not in text:
        raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got {text!r}")
    key, value = text.split("=", 1)
    fields = {f.name: f for f in dataclasses.fields(Config)}
    if key not in fields:
        raise argparse.ArgumentTypeError(
            f"unknown config field {key!r}; fields: {', '.join(sorted(fields))}")
    kind = fields[key].type
    try:
        if kind == "bool":
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(value)
            return key, value.lower() in ("true", "1")
        if kind == "int":
            return key, int(value)
        if kind == "float":
            return key, float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key} expects a {kind}, got {value!r}") from None
    return key, value


def _build_config(args: argparse.Namespace):
    from arlight.pipeline.config import Config

    overrides = dict(args.set or [])
    if getattr(args, "rgb", False):
        overrides["estimate_rgb"] = True
    if getattr(args, "device", None):
        overrides["device"] = args.device
    return Config.from_preset(args.preset, **overrides)


def _open_source(args: argparse.Namespace):
    """(sequence-like with .camera, len(), frame(i)), ground truth or None."""
    from arlight.client.datasets import open_pair, open_sequence

    use_poses = args.poses == "groundtruth"
    if args.path == "synthetic":
        from arlight.pipeline.synthetic import make_sequence

        seq = make_sequence(num_frames=args.max_frames or 12)
        frames = [f if use_poses else dataclasses.replace(f, pose=None) for f in seq.frames]
        return seq.camera, frames, seq
    if args.depth:
        seq = open_pair(args.path, args.depth, args.depth_encoding)
    else:
        seq = open_sequence(args.path, depth_encoding=args.depth_encoding, use_poses=use_poses,
                            max_frames=args.max_frames)
    return seq.camera, seq.frames, None


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def cmd_estimate(args: argparse.Namespace) -> int:
    from arlight.pipeline.pipeline import Pipeline

    config = _build_config(args)
    camera, frames, truth = _open_source(args)
    n = len(frames)
    print(f"arlight estimate: {args.path} ({n} frames, {camera.width}x{camera.height}), "
          f"preset {config.preset}, poses {args.poses}", file=sys.stderr)
    pipeline = Pipeline(config, camera)
    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    errors = []
    try:
        for i in range(n):
            frame = frames[i]
            t0 = time.perf_counter()
            result = pipeline.process(frame)
            ms = (time.perf_counter() - t0) * 1e3
            record = result.to_json_dict()
            record["frame"] = i
            d = result.dominant_direction_camera
            line = (f"[{i + 1:>4}/{n}] t={result.timestamp:.3f}s  light(cam)=({d[0]:+.2f}, "
                    f"{d[1]:+.2f}, {d[2]:+.2f})  intensity={result.intensity:.3g}  "
                    f"conf={result.confidence.value:.2f}  bands={result.confidence.bands_estimated}"
                    f"  {ms:.0f} ms")
            if truth is not None:
                err = _angle_deg(result.dominant_direction_world,
                                 truth.dominant_direction_world[i])
                errors.append(err)
                record["angular_error_deg"] = err
                line += f"  error={err:.1f} deg"
            print(line, flush=True)
            if out:
                out.write(json.dumps(record) + "\n")
    finally:
        if out:
            out.close()
    if errors:
        print(f"median angular error of the dominant light: {np.nanmedian(errors):.1f} deg "
              f"(90th percentile {np.nanpercentile(errors, 90):.1f})", file=sys.stderr)
    if args.out:
        print(f"wrote {n} results to {args.out}", file=sys.stderr)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from arlight.bench import run_pipeline_benchmark

    run_pipeline_benchmark(presets=args.presets, frames=args.frames, warmup=args.warmup,
                           json_path=args.json)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="arlight", description="Probeless light estimation and coherent AR rendering "
                                    "from RGB-D.")
    parser.add_argument("--version", action="version", version=f"arlight {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log details (warnings "
                        "about defaults chosen for the data are shown either way)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    est = sub.add_parser(
        "estimate", help="estimate the lighting of an RGB-D sequence, one JSON line per frame",
        description="Estimate spherical-harmonics lighting per frame. PATH is a TUM RGB-D "
                    "folder, an Open3D/Redwood folder, a 7-Scenes folder, a colour image "
                    "(with --depth, or a *depth* file beside it), or 'synthetic' (the "
                    "built-in scene with known light; the default).")
    est.add_argument("path", nargs="?", default="synthetic", metavar="PATH")
    est.add_argument("--preset", choices=("full", "fast", "mobile"), default="full",
                     help="speed/accuracy preset (default: full, the paper's 'Ours')")
    est.add_argument("--poses", choices=("groundtruth", "track"), default="track",
                     help="'groundtruth': use the data set's camera poses and skip tracking; "
                          "'track' (default): frame-to-model tracking")
    est.add_argument("--rgb", action="store_true", help="also estimate one SH per RGB channel")
    est.add_argument("--out", metavar="FILE", help="write results as JSON lines to FILE")
    est.add_argument("--max-frames", type=int, metavar="N", help="only the first N frames")
    est.add_argument("--depth", metavar="FILE", help="depth image for a single colour image")
    est.add_argument("--depth-encoding", choices=("tum", "mm", "sun", "nyu"),
                     help="depth encoding (default: from the data set's layout or file name)")
    est.add_argument("--device", help="Open3D device for the volume, e.g. CUDA:0 (default CPU:0)")
    est.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                     help="override any Config field, e.g. --set rt_directions=128")
    est.set_defaults(func=cmd_estimate)

    bench = sub.add_parser("bench", help="per-stage milliseconds for 640x480 frames, per preset",
                           description="Benchmark the pipeline on the built-in synthetic scene "
                                       "(640x480): per-stage median and spread in the rows of "
                                       "the paper's table 1, and frames per second.")
    bench.add_argument("--presets", nargs="+", default=["full", "fast"],
                       choices=("full", "fast", "mobile"))
    bench.add_argument("--frames", type=int, default=8, help="timed frames per preset")
    bench.add_argument("--warmup", type=int, default=2, help="untimed frames first (JIT, caches)")
    bench.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    bench.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    from arlight.client.datasets import DatasetError
    from arlight.pipeline.pipeline import FrameError

    try:
        return args.func(args)
    except (DatasetError, FrameError, ValueError, OSError) as exc:
        print(f"arlight {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
