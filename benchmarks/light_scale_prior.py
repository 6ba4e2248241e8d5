"""The real-albedo prior that turns a light estimate into radiance for the renderer.

The light estimate knows albedo x light only (it fits I = T . l with unit albedo), so the
renderer shades a virtual albedo against a prior mean albedo rho of the real scene: light in
linear image units = l pi / rho (`render_real_albedo`). The rho that makes the estimate
right for a virtual object is the one for which the estimated irradiance on the normals an
object shows the camera equals the truth's: per frame,

    rho = mean E_est(n) / mean E_gt(n)  over unit normals n turned towards the camera,

E the clamped-cosine irradiance of each SH (the estimate with unit albedo, the truth of
lighting_gt.json with the sequence's exposure applied). This prints its median over frames
for each ground-truth sequence, the median over the sequences (the prior), and the
leave-one-sequence-out medians, which show how much the prior depends on any one scene.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/light_scale_prior.py [SEQ ...]
                                            [--frames 8] [--preset full]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from arlight.pipeline import sh
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.runtime import configure_process
from arlight.sources.sequence import open_sequence

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic"


def implied_albedo(estimate_sh: np.ndarray, truth_sh: np.ndarray,
                   camera_forward_world: np.ndarray, samples: int = 2000) -> float:
    """rho for one frame: estimated over true irradiance, averaged over the world-frame unit
    normals that face the camera (n . forward < 0)."""
    dirs = sh.fibonacci_sphere(samples)
    facing = dirs[dirs @ camera_forward_world < 0.0]
    e_est = sh.evaluate(sh.irradiance_from_radiance(estimate_sh), facing).mean()
    e_gt = sh.evaluate(sh.irradiance_from_radiance(truth_sh), facing).mean()
    return float(e_est / e_gt)


def sequence_albedo(folder: Path, frames: int, preset: str) -> float:
    """Median over the sequence's first `frames` frames of `implied_albedo`."""
    truth = json.loads((folder / "lighting_gt.json").read_text())
    seq = open_sequence(folder, use_poses=True, max_frames=frames)
    pipeline = Pipeline(Config.from_preset(preset), seq.camera)
    values = []
    for index, frame in enumerate(seq.frames):
        result = pipeline.process(frame)
        f = truth["frames"][index]
        l_gt = sh.toggle_condon_shortley(np.asarray(f["sh_lum_world"])) * truth["exposure_scale"]
        forward = result.pose[:3, :3] @ np.array([0.0, 0.0, 1.0])
        values.append(implied_albedo(np.asarray(result.sh) * math.pi, l_gt, forward))
    return float(np.median(values))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", nargs="*", type=Path,
                        help="sequence folders with lighting_gt.json (default: all shared)")
    parser.add_argument("--frames", type=int, default=8, help="frames per sequence")
    parser.add_argument("--preset", default="full", help="pipeline preset")
    args = parser.parse_args(argv)
    configure_process()
    folders = args.sequences or sorted(p.parent for p in DATA.glob("*/lighting_gt.json"))
    if not folders:
        print(f"no ground-truth sequences (looked in {DATA})", file=sys.stderr)
        return 2
    rho = {}
    for folder in folders:
        rho[folder.name] = sequence_albedo(folder, args.frames, args.preset)
        print(f"{folder.name:40s} implied albedo {rho[folder.name]:.3f}", flush=True)
    values = np.array(list(rho.values()))
    loo = [float(np.median(np.delete(values, i))) for i in range(len(values))]
    print(f"median over {len(values)} sequences: {np.median(values):.3f} "
          f"(leave one sequence out: {min(loo):.3f} .. {max(loo):.3f}; "
          f"spread over sequences {values.min():.3f} .. {values.max():.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
