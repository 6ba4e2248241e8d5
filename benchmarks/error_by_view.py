"""The light's error by where the light stands relative to the view: back-lit views.

    python benchmarks/error_by_view.py SEQ [SEQ ...] [--preset fast] [--set KEY=VALUE]
        [--json FILE]

For each ground-truth sequence (lighting_gt.json with `dominant_dir_upper_world`; sequences
whose truth is a probe inside a room are skipped), the Pipeline runs every frame with the
true poses. Per frame: the angular error of the reported dominant direction against the
upper-hemisphere truth, the error in elevation (estimate minus truth, degrees above the
ground plane, world +Y up as the generator's convention says) and in azimuth, and how far
(degrees of azimuth) the true light stands from the direction the camera looks. Prints the
median error and elevation bias by that angle (0: the camera looks towards the light, a
back-lit view) and by the light's true elevation.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from arlight.cli.common import config_override

VIEW_BINS = ((0, 45), (45, 90), (90, 135), (135, 181))
ELEVATION_BINS = ((0, 30), (30, 50), (50, 70), (70, 91))


def elevation_deg(v: np.ndarray) -> float:
    """Degrees above the ground plane (world +Y up)."""
    return math.degrees(math.asin(float(np.clip(v[1] / np.linalg.norm(v), -1.0, 1.0))))


def azimuth_deg(v: np.ndarray) -> float:
    """Degrees about +Y, from +Z towards +X."""
    return math.degrees(math.atan2(float(v[0]), float(v[2])))


def wrapped(angle_deg: float) -> float:
    """The angle in (-180, 180]."""
    return (angle_deg + 180.0) % 360.0 - 180.0


def frame_row(estimate: np.ndarray, truth: np.ndarray, forward: np.ndarray) -> dict:
    """One frame's figures (world-frame unit vectors; forward: the camera's +z in the world)."""
    cos = float(estimate @ truth / (np.linalg.norm(estimate) * np.linalg.norm(truth)))
    return {
        "error": math.degrees(math.acos(min(1.0, max(-1.0, cos)))),
        "elevation_bias": elevation_deg(estimate) - elevation_deg(truth),
        "azimuth_error": wrapped(azimuth_deg(estimate) - azimuth_deg(truth)),
        "light_from_view": abs(wrapped(azimuth_deg(truth) - azimuth_deg(forward))),
        "true_elevation": elevation_deg(truth),
    }


def binned(rows: list[dict], key: str, bins) -> list[tuple[str, int, float, float]]:
    """Per bin of rows[key]: (label, frames, median error, median elevation bias)."""
    out = []
    for lo, hi in bins:
        sel = [r for r in rows if lo <= r[key] < hi]
        if sel:
            out.append(
                (
                    f"{lo}-{min(hi, 180 if key == 'light_from_view' else 90)}",
                    len(sel),
                    float(np.median([r["error"] for r in sel])),
                    float(np.median([r["elevation_bias"] for r in sel])),
                )
            )
    return out


def measure(folders: list[Path], preset: str, overrides: dict | None = None) -> list[dict]:
    """Every frame's `frame_row`, with its sequence and index."""
    from arlight.pipeline.config import Config
    from arlight.pipeline.pipeline import Pipeline
    from arlight.sources.sequence import open_sequence

    rows = []
    for folder in folders:
        truth = json.loads((folder / "lighting_gt.json").read_text())
        if truth.get("truth_reference") == "probe":
            continue
        seq = open_sequence(folder, use_poses=True)
        pipeline = Pipeline(Config.from_preset(preset, **(overrides or {})), seq.camera)
        for index, frame in enumerate(seq.frames):
            result = pipeline.process(frame)
            forward = np.asarray(result.pose)[:3, :3] @ np.array([0.0, 0.0, 1.0])
            row = frame_row(
                np.asarray(result.dominant_direction_world, np.float64),
                np.asarray(truth["frames"][index]["dominant_dir_upper_world"], np.float64),
                forward,
            )
            rows.append(
                {
                    "sequence": folder.name,
                    "frame": index,
                    "env_map": truth["frames"][index].get("env_map"),
                    "estimate_world": [float(x) for x in result.dominant_direction_world],
                    "forward_world": [float(x) for x in forward],
                    "confidence": float(result.confidence.value),
                    **row,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", nargs="+", type=Path, metavar="SEQ")
    parser.add_argument("--preset", default="fast", choices=("full", "fast", "mobile"))
    parser.add_argument(
        "--set", action="append", default=[], type=config_override, metavar="KEY=VALUE"
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the rows to FILE")
    args = parser.parse_args(argv)
    overrides = dict(args.set)
    missing = [str(s) for s in args.sequences if not (s / "lighting_gt.json").is_file()]
    if missing:
        parser.error(f"no lighting_gt.json in {', '.join(missing)}")
    from arlight.pipeline.runtime import configure_process

    configure_process()
    rows = measure(args.sequences, args.preset, overrides)
    if not rows:
        parser.error("no sequence with a distant-light truth")
    bias = np.array([r["elevation_bias"] for r in rows])
    print(
        f"{len(rows)} frames, `{args.preset}`: elevation estimate - truth"
        f" median {np.median(bias):+.1f} degrees (p10 {np.percentile(bias, 10):+.1f},"
        f" p90 {np.percentile(bias, 90):+.1f}),"
        f" the estimate higher in {np.mean(bias > 0):.0%} of frames"
    )
    for title, key, bins in (
        ("light's azimuth from the view direction", "light_from_view", VIEW_BINS),
        ("light's true elevation", "true_elevation", ELEVATION_BINS),
    ):
        print(f"| {title} (deg) | frames | median error | median elevation bias |")
        print("|---|---|---|---|")
        for label, count, error, b in binned(rows, key, bins):
            print(f"| {label} | {count} | {error:.1f} | {b:+.1f} |")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
