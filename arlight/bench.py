"""Pipeline benchmark: per-stage milliseconds in the rows of the paper's table 1.

Never a single call: warm-up frames first (JIT compilation, caches), then median and
spread over the timed frames; every preset runs in the same process on the same frames so
the ratios compare like with like. Seeds are fixed (built-in synthetic scene, seed 0).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time

import numpy as np

from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import STAGES, Pipeline
from arlight.sources.synthetic import make_sequence


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=False, cwd=os.path.dirname(__file__)
                              ).stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def run_pipeline_benchmark(presets: list[str], frames: int = 8, warmup: int = 2,
                           json_path: str | None = None) -> dict:
    """Time `frames` frames per preset after `warmup` untimed ones; print a table."""
    seq = make_sequence(num_frames=warmup + frames)
    record = {"commit": _commit(), "machine": platform.machine(), "cpus": os.cpu_count(),
              "python": sys.version.split()[0], "frames": frames, "warmup": warmup,
              "resolution": [seq.camera.width, seq.camera.height], "presets": {}}
    print(f"arlight bench: {seq.camera.width}x{seq.camera.height}, {frames} timed frames "
          f"after {warmup} warm-up, poses given (tracking skipped), {os.cpu_count()} CPUs",
          file=sys.stderr)
    for preset in presets:
        pipeline = Pipeline(Config.from_preset(preset), seq.camera)
        per_stage: dict[str, list[float]] = {s: [] for s in STAGES}
        totals = []
        for i, frame in enumerate(seq.frames):
            t0 = time.perf_counter()
            result = pipeline.process(frame)
            total = (time.perf_counter() - t0) * 1e3
            print(f"  {preset}: frame {i + 1}/{len(seq.frames)} {total:.0f} ms"
                  + (" (warm-up)" if i < warmup else ""), file=sys.stderr, flush=True)
            if i < warmup:
                continue
            totals.append(total)
            for s in STAGES:
                per_stage[s].append(result.timings_ms.get(s, 0.0))
        stats = {s: {"median_ms": float(np.median(v)), "p10_ms": float(np.percentile(v, 10)),
                     "p90_ms": float(np.percentile(v, 90))} for s, v in per_stage.items()}
        stats["Update"] = {"median_ms": float(np.median(totals)),
                           "p10_ms": float(np.percentile(totals, 10)),
                           "p90_ms": float(np.percentile(totals, 90))}
        stats["FPS"] = 1000.0 / stats["Update"]["median_ms"]
        record["presets"][preset] = stats
    _print_table(record)
    if json_path:
        with open(json_path, "w") as f:
            json.dump(record, f, indent=1)
    return record


def _print_table(record: dict) -> None:
    presets = list(record["presets"])
    print(f"{'stage (ms, median [p10-p90])':<30}" + "".join(f"{p:>24}" for p in presets))
    for row in ("FPS", "Update", *STAGES):
        cells = []
        for p in presets:
            v = record["presets"][p][row]
            cells.append(f"{v:.2f}" if row == "FPS" else
                         f"{v['median_ms']:.1f} [{v['p10_ms']:.0f}-{v['p90_ms']:.0f}]")
        print(f"{row:<30}" + "".join(f"{c:>24}" for c in cells))
    if len(presets) > 1:
        base = record["presets"][presets[0]]["Update"]["median_ms"]
        for p in presets[1:]:
            ratio = base / record["presets"][p]["Update"]["median_ms"]
            print(f"speed-up {p} vs {presets[0]}: {ratio:.2f}x")
