"""Milliseconds of the compact-source fit (pipeline.compact_light) on recorded inputs.

    python benchmarks/compact_cost.py CACHE/SEQUENCE.npz [--frames 3]

CACHE is a `light_replay.py record` cache (it holds the fitted pixels' geometry and the
volume's mesh). Per search setting (candidates x search pixels): the median milliseconds of
`fit_compact_source` over the frames, the rays it cast and what it found. Set
OPENBLAS_NUM_THREADS=1 as the CLI does; say what else the machine was running.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from arlight.pipeline.compact_light import ShadowTester, fit_compact_source
from arlight.pipeline.config import Config
from arlight.pipeline.object_space_transfer import OcclusionScene, SurfaceMesh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run as a script
from benchmarks.light_replay import estimate_recorded  # noqa: E402

SETTINGS = ((256, 4000), (128, 2000), (64, 1000))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", help="one sequence's .npz of a light_replay cache")
    parser.add_argument("--frames", type=int, default=3)
    args = parser.parse_args(argv)
    params = Config.from_preset("full").estimation
    try:
        data = np.load(args.recording)
        meta = json.loads(str(data["meta"]))
    except (OSError, ValueError, KeyError) as exc:
        parser.error(f"{args.recording}: not a light_replay recording ({exc})")
    frames = []
    for i, m in enumerate(meta[: args.frames]):
        est = estimate_recorded(data, i, m, params)
        mesh = SurfaceMesh(data[f"{i}_mesh_vertices"], data[f"{i}_mesh_triangles"], True)
        frames.append((i, m, est.fit, OcclusionScene(mesh)))
    for candidates, samples in SETTINGS:
        times, rays, reason = [], 0, ""
        for i, m, f, scene in frames:
            t0 = time.perf_counter()
            tester = ShadowTester(
                [(scene, np.eye(4))],
                data[f"{i}_points"][f.rows].astype(np.float64),
                data[f"{i}_normals"][f.rows].astype(np.float64),
            )
            fit = fit_compact_source(
                f.design,
                f.albedo,
                f.weights,
                f.lum,
                None,
                f.penalty,
                f.bands,
                tester,
                np.asarray(m["up"]),
                candidates=candidates,
                search_samples=samples,
            )
            times.append(1e3 * (time.perf_counter() - t0))
            rays, reason = tester.rays, fit.reason
        print(
            f"{candidates:4d} x {samples:5d}: {np.median(times):6.0f} ms  {rays} rays  "
            f"(last frame: {reason[:60]})",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
