"""Milliseconds of the compact-source stage inside the pipeline, on the built-in scene.

    .venv/bin/python benchmarks/compact_stage_ms.py [--presets fast full] [--frames 12]
        [--set KEY=VALUE ...]

Runs `Pipeline.process` over the built-in scene (640x480, poses given, as `arlight bench`)
with compact_sources=1 and times, per frame after two of warm-up, the two parts of the
stage apart: the occluder (the volume's mesh and its BVH, rebuilt every aux_update_interval
fused frames, else cached) taken in the front half, and the fit itself
(`CompactLightStage.fit_against`: the rays and the closed-form scores) in the back half.
Prints their medians (and the occluder's on the frames that rebuilt it; the fit's process
CPU time over its wall time: the cores it keeps busy) beside LightEst's.
One BLAS thread, as the `arlight` command; say what else the machine was running.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before NumPy: as the arlight command

import argparse  # noqa: E402
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from arlight.cli.common import config_override
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.runtime import configure_process
from arlight.sources.synthetic import make_sequence

WARMUP = 2


def _timed(into: list[tuple[float, float]], call: Callable[..., Any]) -> Callable[..., Any]:
    """`call`, its (wall-clock, process CPU) milliseconds appended to `into` at each call."""

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return call(*args, **kwargs)
        finally:
            into.append(((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3))

    return wrapper


def measure(preset: str, frames: int, overrides: dict[str, Any]) -> dict[str, float]:
    """Median ms per frame after WARMUP: occluder, occluder when rebuilt, fit, the fit's
    CPU ms over its wall ms (cores busy), LightEst."""
    config = Config.from_preset(preset, compact_sources=1, **overrides)
    seq = make_sequence(num_frames=frames + WARMUP, width=640, height=480)
    pipeline = Pipeline(config, seq.camera)
    stage = pipeline.light.compact()
    occluder_ms: list[tuple[float, float]] = []
    fit_ms: list[tuple[float, float]] = []
    builds: list[int] = []
    scenes = stage._scenes
    stage.occluder = _timed(occluder_ms, stage.occluder)  # type: ignore[method-assign]
    stage.fit_against = _timed(fit_ms, stage.fit_against)  # type: ignore[method-assign]
    light_ms = []
    for frame in seq.frames:
        before = scenes.builds
        result = pipeline.process(frame)
        builds.append(scenes.builds - before)
        light_ms.append(result.timings_ms["LightEst"])
    kept = slice(WARMUP, None)
    occluder = np.array(occluder_ms[kept])[:, 0]
    rebuilt = occluder[np.array(builds[kept]) > 0]
    fit = np.array(fit_ms[kept]).reshape(-1, 2)  # (a frame without a fit has no row)
    nan = float("nan")
    return {
        "occluder": float(np.median(occluder)),
        "occluder rebuilt": float(np.median(rebuilt)) if len(rebuilt) else nan,
        "fit": float(np.median(fit[:, 0])) if len(fit) else nan,
        "fit cores": float(np.sum(fit[:, 1]) / np.sum(fit[:, 0])) if len(fit) else nan,
        "LightEst": float(np.median(light_ms[kept])),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["fast", "full"])
    parser.add_argument("--frames", type=int, default=12, help="timed frames (default 12)")
    parser.add_argument(
        "--set", action="append", default=[], type=config_override, metavar="KEY=VALUE"
    )
    args = parser.parse_args(argv)
    configure_process()
    try:
        overrides = dict(args.set)
        for preset in args.presets:
            Config.from_preset(preset, compact_sources=1, **overrides)
    except ValueError as exc:
        parser.error(f"--set: {exc}")
    print("| preset | occluder ms | occluder rebuilt ms | fit ms | fit: cores busy | LightEst ms |")
    print("|---|---|---|---|---|---|")
    for preset in args.presets:
        ms = measure(preset, args.frames, overrides)
        print(
            f"| {preset} | {ms['occluder']:.1f} | {ms['occluder rebuilt']:.1f} "
            f"| {ms['fit']:.1f} | {ms['fit cores']:.2f} | {ms['LightEst']:.1f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
