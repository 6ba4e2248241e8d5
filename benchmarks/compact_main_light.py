"""The engine layouts' main light against the true sun, with and without compact sources.

    nice -n 10 .venv/bin/python benchmarks/compact_main_light.py --seeds 6 --frames 3

For each seed, the synthetic sunny scene (sources/synthetic.py: a delta sun with hard
shadows, a quadratic sky, a camera held still at 320 x 240, no sensor noise) goes through
the `fast` pipeline twice: SH only (compact_sources 0, the default) and with compact sources
(compact_sources 1). Per frame, the `main_light` layout the server sends (camera frame,
OpenGL axes, via server.results.result_message) is turned back into the world and compared
with the true sun; beside it the whole sphere's first moment (what main_light gave before
the Result's direction was used). The intensity is compared unit-free: the main light's
luminance over the SH's band 0, against the true sun's integrated radiance over the true
SH's band 0; and the kept source's `share` against the true sun's share of the irradiance
on a surface facing it. Printed: median and max per variant, and how often a source was kept.
Results: docs/results/compact-exports.md.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from arlight.pipeline import sh
from arlight.pipeline.config import Config
from arlight.pipeline.engine_export import camera_exports
from arlight.pipeline.pipeline import Pipeline
from arlight.server.results import result_message
from arlight.sources.synthetic import SUN_RGB, make_sequence

GL_FROM_CV = np.diag([1.0, -1.0, -1.0])
LUMA = np.array([0.2126, 0.7152, 0.0722])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def _run(seed: int, frames: int, compact: int) -> list[dict]:
    seq = make_sequence(
        num_frames=frames, width=320, height=240, seed=seed, sensor_noise=False, held=True
    )
    pipeline = Pipeline(Config.from_preset("fast", compact_sources=compact), seq.camera)
    rows = []
    for i, frame in enumerate(seq.frames):
        got = pipeline.process(frame)
        msg = result_message(
            got,
            seq=i,
            counters=(i + 1, i + 1, 0),
            receive_time_wall=0.0,
            finish_time_wall=0.0,
            exports=("main_light",),
        )
        assert msg.exports is not None
        main = msg.exports["main_light"]
        rotation = got.pose[:3, :3]
        world = rotation @ GL_FROM_CV @ np.asarray(main["direction"])
        sun = seq.sun_direction_world[i]
        light = got.sh if got.sh_rgb is None else got.sh_rgb
        whole = camera_exports(light, got.pose, ["main_light"])["main_light"]
        whole_world = rotation @ GL_FROM_CV @ np.asarray(whole["direction"])
        k_true = float(LUMA @ SUN_RGB)
        true_ratio = k_true / float(seq.sh_world[i][0])
        sky = seq.sh_world[i] - sh.directional_light(sun, k_true, 4)
        sky_e = float(sh.evaluate(sh.irradiance_from_radiance(sky), sun[None])[0])
        share = got.compact_sources[0].share if got.compact_sources else math.nan
        rows.append(
            {
                "main_deg": _angle_deg(world, sun),
                "whole_deg": _angle_deg(whole_world, sun),
                "kept": len(got.compact_sources),
                "ratio": float(LUMA @ np.asarray(main["intensity"])) / float(got.sh[0]),
                "true_ratio": true_ratio,
                "share": share,
                "true_share": k_true / (k_true + sky_e),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=6, help="synthetic scenes (seeds 0..N-1)")
    ap.add_argument("--frames", type=int, default=3, help="frames per scene")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.frames < 1:
        ap.error("--seeds and --frames must be >= 1")
    print(
        "variant            main light vs sun (deg)   whole sphere (deg)   kept   "
        "intensity / band 0 (true)"
    )
    for name, compact in (("SH only", 0), ("compact sources", 1)):
        rows = [r for seed in range(args.seeds) for r in _run(seed, args.frames, compact)]
        main_deg = np.array([r["main_deg"] for r in rows])
        whole = np.array([r["whole_deg"] for r in rows])
        ratio = np.array([r["ratio"] for r in rows])
        truth = np.array([r["true_ratio"] for r in rows])
        kept = sum(r["kept"] > 0 for r in rows)
        share = np.array([r["share"] for r in rows])
        true_share = np.array([r["true_share"] for r in rows])
        print(
            f"{name:18s} median {np.median(main_deg):5.1f} max {main_deg.max():5.1f}"
            f"      median {np.median(whole):5.1f} max {whole.max():5.1f}"
            f"   {kept:2d}/{len(rows):2d}"
            f"   median {np.median(ratio):6.2f} ({np.median(truth):6.2f})"
            + (
                f"   share median {np.nanmedian(share):.2f} ({np.median(true_share):.2f})"
                if kept
                else ""
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
