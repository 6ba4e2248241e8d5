"""The reflection probe's cost per frame (issue 33, item 5), by part, at several sizes.

On one sequence with a mirror object (default: a corpus room), the `fast` Pipeline runs
--frames frames (the grid fused as in a session); then, on the last frame, each part is
timed --repeat times after a warm-up: fuse (carving and fusing the frame into the room
grid), probe (following every texel direction and the distant light of the misses; the
Probe stage is fuse + probe), prefilter (the GGX mips, made when a glossy object or a
client reads them: a scene of mirrors does not pay it) and shade (the virtual pixels of the
mirror / glossy objects shaded from the probe, part of the Rendering stage). Prints median,
p10 and p90 milliseconds per part and size and writes a JSON record (commit, machine, load average)
beside them. Never time a single call: the figures are of the same inputs, repeated.

    nice -n 10 .venv/bin/python benchmarks/probe_speed.py [SEQ] [--sizes 64 128]
        [--frames 3] [--repeat 15] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from arlight.pipeline import probe_cube
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.probe import DistantLight, ProbeSettings, ProbeStage
from arlight.pipeline.runtime import configure_process
from arlight.report import commit as git_commit
from arlight.sources.sequence import open_sequence
from arlight.sources.virtual_scene_file import load_virtual_scene

DEFAULT_SEQ = Path.home() / ".cache" / "arlight" / "corpus" / "c021_room_st_peters_square_night"
PARTS = ("fuse", "probe", "prefilter", "shade", "total")


def _timed(fn, repeat: int) -> list[float]:
    fn()  # warm-up (JIT, caches)
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def measure_size(folder: Path, size: int, frames: int, repeat: int, preset: str) -> dict:
    """{part: [ms, ...]} at one probe size on the sequence's frame `frames - 1`."""
    seq = open_sequence(folder, use_poses=True, max_frames=frames)
    scene = load_virtual_scene(folder / "ar" / "virtual_scene.json")
    pipe = Pipeline(Config.from_preset(preset, probe_size=size), seq.camera, scene)
    for frame in seq.frames:
        pipe.process(frame)
    if pipe.last_render is None or pipe.last_probe is None or pipe._renderer is None:
        raise SystemExit(f"{folder}: no probe was made (no mirror or glossy object placed)")
    inputs, output = pipe.last_render
    probe = pipe.last_probe
    stage = ProbeStage(pipe._probe.settings if pipe._probe else ProbeSettings(size), seq.camera)
    distant = DistantLight(inputs.light_sh, inputs.light_rgb)
    point, pose = probe.point_world, inputs.world_from_cam
    renderer = pipe._renderer
    vs, us = np.nonzero(output.virtual_mask)
    irradiance = np.ones((len(vs), 3))

    def fuse() -> None:
        stage.fuse(point, inputs.depth_m, inputs.color_linear, pose)

    def make() -> None:
        stage.probe(point, pose, distant)

    def shade() -> None:
        rgb = np.zeros((len(vs), 3))
        renderer._probe_reflecting(probe, output.gbuffer, vs, us, irradiance, pose, rgb)

    def prefilter() -> None:  # what a glossy object or a client asking mips adds
        probe_cube.prefilter(probe.radiance)

    parts = {"fuse": _timed(fuse, repeat), "probe": _timed(make, repeat)}
    parts["prefilter"] = _timed(prefilter, repeat)
    parts["shade"] = _timed(shade, repeat)
    parts["total"] = list(np.sum([parts[k] for k in ("fuse", "probe", "prefilter", "shade")], 0))
    return parts


def measure(folder: Path, sizes: list[int], frames: int, repeat: int, preset: str) -> dict:
    """{size: {part: [ms, ...]}}."""
    return {size: measure_size(folder, size, frames, repeat, preset) for size in sizes}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", nargs="?", type=Path, default=DEFAULT_SEQ)
    parser.add_argument("--sizes", nargs="+", type=int, default=[64, 128])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=15)
    parser.add_argument("--preset", default="fast", choices=("full", "fast", "mobile"))
    parser.add_argument(
        "--json", type=Path, default=None, help="also write the record to FILE (default: none)"
    )
    args = parser.parse_args(argv)
    if not (args.sequence / "ar" / "virtual_scene.json").is_file():
        parser.error(f"{args.sequence} has no ar/virtual_scene.json (render one: arlight synth)")
    for s in args.sizes:
        try:
            ProbeSettings(size=s)
        except ValueError as exc:
            parser.error(f"--sizes: {exc}")
    configure_process()
    load_before = os.getloadavg()
    figures = measure(args.sequence, args.sizes, args.frames, args.repeat, args.preset)
    load_after = os.getloadavg()
    print(f"| size | {' | '.join(PARTS)} |")
    print("|---|" + "---|" * len(PARTS))
    for size, parts in figures.items():
        cells = [
            f"{np.median(parts[p]):.1f} ({np.percentile(parts[p], 10):.1f}-"
            f"{np.percentile(parts[p], 90):.1f})"
            for p in PARTS
        ]
        print(f"| {size} | " + " | ".join(cells) + " |")
    print("ms: median (p10-p90) over", args.repeat, "repeats; load average", load_before[0])
    commit = git_commit()
    record = {
        "sequence": str(args.sequence),
        "preset": args.preset,
        "commit": commit,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "load_average_1min": [load_before[0], load_after[0]],
        "ms": {str(k): v for k, v in figures.items()},
    }
    if args.json is not None:  # not into the working folder unasked (a checkout, often)
        args.json.write_text(json.dumps(record, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
