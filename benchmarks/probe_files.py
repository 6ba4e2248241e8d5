"""What `--probe-out DIR` costs a frame (arlight stream, arlight estimate): milliseconds to
write one probe as OpenEXR faces of every level plus its JSON (arlight/cli/probe_files.py),
at several sizes, level 0 alone and every level, in the world layout (the faces as they are)
and an engine's (resampled into a tilted camera's frame: probe_faces, bilinear per level).

The probe is random HDR texels (the cost does not depend on them); each case is written
--repeat times after a warm-up into a temporary folder. Prints a Markdown table (median ms
with p10-p90) and the commit, machine and load average.

    nice -n 10 .venv/bin/python benchmarks/probe_files.py [--sizes 64 128] [--repeat 15]
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from arlight.cli.client_options import probe_size
from arlight.cli.probe_files import write_probe_files
from arlight.protocols.probe import ProbeCube, num_levels
from arlight.report import commit as git_commit


def tilted_pose() -> np.ndarray:
    """4 x 4 camera-to-world turned 30 degrees about y and 20 about x (no axis-aligned
    shortcut in probe_faces)."""
    a, b = np.radians(30.0), np.radians(20.0)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    pose = np.eye(4)
    pose[:3, :3] = ry @ rx
    return pose


def random_cube(size: int, levels: int, seed: int = 0) -> ProbeCube:
    rng = np.random.default_rng(seed)
    data = [
        rng.uniform(0.0, 4.0, (6, size >> k, size >> k, 3)).astype(np.float32)
        for k in range(levels)
    ]
    roughness = list(np.linspace(0.0, 1.0, levels)) if levels > 1 else [0.0]
    return ProbeCube([0.0, 0.0, 1.0], data, roughness)


def measure(cube: ProbeCube, layout: str, repeat: int) -> list[float]:
    """Milliseconds of each of `repeat` writes (after one untimed)."""
    pose = tilted_pose()
    times = []
    with tempfile.TemporaryDirectory() as folder:
        write_probe_files(Path(folder) / "warm", cube, cube.point_world, layout, pose, {})
        for i in range(repeat):
            start = time.perf_counter()
            write_probe_files(Path(folder) / f"{i:06d}", cube, cube.point_world, layout, pose, {})
            times.append((time.perf_counter() - start) * 1e3)
    return times


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", type=probe_size, default=[64, 128])
    parser.add_argument("--repeat", type=int, default=15)
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    load_before = os.getloadavg()
    print("| texels a face | levels | layout | files | ms a frame, median (p10-p90) |")
    print("|---|---|---|---|---|")
    for size in args.sizes:
        for levels in (1, num_levels(size)):
            cube = random_cube(size, levels)
            for layout in ("world", "threejs"):
                t = measure(cube, layout, args.repeat)
                p10, p50, p90 = np.percentile(t, [10, 50, 90])
                print(
                    f"| {size} | {levels} | {layout} | {6 * levels + 1} | "
                    f"{p50:.1f} ({p10:.1f}-{p90:.1f}) |",
                    flush=True,
                )
    commit = git_commit()
    print(
        f"\ncommit {commit}, {platform.processor() or platform.machine()}, {os.cpu_count()} "
        f"cores, load average {load_before[0]:.1f} before / {os.getloadavg()[0]:.1f} after"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
