"""How busy each stage keeps the cores: wall-clock and process CPU milliseconds per stage.

What overlapping consecutive frames could gain (issue 35 item 2) is bounded by the cores the
stages leave idle: a frame using `util` cores of `cores` can at best run cores / util times
as often when frames overlap. The pipeline's `checkpoint` hook (called before each stage)
marks the stage boundaries; the process's CPU time between them is that stage's, on every
thread (Numba's, Open3D's, OpenCV's and the side thread's).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/stage_cpu.py [--presets fast full]
        [--frames 12] [--size 640x480]

(one BLAS thread, as the `arlight` command sets before NumPy loads: arlight/cli/__init__.py)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before NumPy: as the arlight command

import argparse  # noqa: E402
import sys
import time

import numpy as np

from arlight.bench import BUILT_IN, open_data
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.runtime import configure_process
from arlight.sources.synthetic import parse_size

# the segments between the checkpoints, in the order the pipeline passes them
SEGMENTS = ("Input", "Reconstruct+Surface", "DynGeo", "RadTransfer", "LightEst", "Probe")
MARKS = {"Reconstruct": 1, "DynGeo": 2, "RadTransfer": 3, "LightEst": 4, "Probe": 5}


class StageClock:
    """The checkpoint hook: wall and CPU seconds spent in each segment of one frame."""

    def __init__(self) -> None:
        self.wall = np.zeros(len(SEGMENTS) + 1)
        self.cpu = np.zeros(len(SEGMENTS) + 1)
        self._segment = 0
        self._t = (time.perf_counter(), time.process_time())

    def __call__(self, stage: str) -> None:
        segment = MARKS.get(stage)
        if segment is None or segment <= self._segment:
            return  # LightEst's robust iterations call it again; Rendering ends the frame
        self._close(segment)

    def _close(self, next_segment: int) -> None:
        now = (time.perf_counter(), time.process_time())
        self.wall[self._segment] += now[0] - self._t[0]
        self.cpu[self._segment] += now[1] - self._t[1]
        self._segment, self._t = next_segment, now

    def finish(self) -> None:
        self._close(len(SEGMENTS))


def measure(preset: str, frames: int, warmup: int, size: tuple[int, int]) -> None:
    scene = open_data([BUILT_IN], frames, warmup, size)[0]  # as `arlight bench` sees it
    pipeline = Pipeline(Config.from_preset(preset), scene.camera)
    wall, cpu = [], []
    for i, frame in enumerate(scene.frames):
        clock = StageClock()
        t0, c0 = time.perf_counter(), time.process_time()
        pipeline.process(frame, checkpoint=clock)
        clock.finish()
        if i >= warmup:
            wall.append(np.append(clock.wall[: len(SEGMENTS)], time.perf_counter() - t0))
            cpu.append(np.append(clock.cpu[: len(SEGMENTS)], time.process_time() - c0))
    w, c = np.median(wall, axis=0) * 1e3, np.median(cpu, axis=0) * 1e3
    cores = os.cpu_count() or 1
    print(f"\n{preset} at {size[0]}x{size[1]}, {frames} frames (median), {cores} cores")
    print("| stage | wall ms | CPU ms | cores busy |")
    print("|---|---|---|---|")
    for name, wi, ci in zip((*SEGMENTS, "frame"), w, c, strict=True):
        print(f"| {name} | {wi:.1f} | {ci:.1f} | {ci / max(wi, 1e-9):.2f} |")
    util = c[-1] / max(w[-1], 1e-9)
    print(
        f"frames overlapped could run at most {cores / util:.2f}x as often "
        f"({1e3 / w[-1]:.2f} -> {cores / util * 1e3 / w[-1]:.2f} FPS), a frame's latency "
        f"staying {w[-1]:.0f} ms or more"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["fast", "full"])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--size", default="640x480", help="WxH of the built-in scene")
    args = parser.parse_args(argv)
    configure_process()  # the threading the CLI and the server use
    try:
        size = parse_size(args.size)
        configs = [Config.from_preset(p) for p in args.presets]
    except ValueError as exc:
        print(f"stage_cpu: {exc}", file=sys.stderr)
        return 2
    for config in configs:
        measure(config.preset.value, args.frames, args.warmup, size)
    return 0


if __name__ == "__main__":
    sys.exit(main())
