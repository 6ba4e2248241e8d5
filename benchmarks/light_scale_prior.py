"""The real-albedo prior and the light colour that turn a light estimate into radiance for
the renderer.

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

The light's colour (the per-channel factor the renderer gives the light) is measured in the
same run: the angle (degrees) between the truth's band-0 RGB (lighting_gt.json
sh_rgb_world) and (a) white, the default, (b) the fit's own per-channel estimate
(`estimate_rgb`: each channel fitted with the luminance fit's albedos, i.e. every material
taken as grey), (c) the mean linear colour of the fitted pixels (grey world); median over
frames, then over sequences.

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
from arlight.pipeline.color import LUMA
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.rendering import luminance_light_rgb
from arlight.pipeline.runtime import configure_process
from arlight.sources.sequence import open_sequence

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic"


def implied_albedo(
    estimate_sh: np.ndarray,
    truth_sh: np.ndarray,
    camera_forward_world: np.ndarray,
    samples: int = 2000,
) -> float:
    """rho for one frame: estimated over true irradiance, averaged over the world-frame unit
    normals that face the camera (n . forward < 0)."""
    dirs = sh.fibonacci_sphere(samples)
    facing = dirs[dirs @ camera_forward_world < 0.0]
    e_est = sh.evaluate(sh.irradiance_from_radiance(estimate_sh), facing).mean()
    e_gt = sh.evaluate(sh.irradiance_from_radiance(truth_sh), facing).mean()
    return float(e_est / e_gt)


COLOUR_CHOICES = ("white", "estimate_rgb", "grey_world")


def colour_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Angle (degrees) between two RGB triples: the error of a light's colour, whatever
    its intensity."""
    c = float(estimate @ truth) / max(
        float(np.linalg.norm(estimate) * np.linalg.norm(truth)), 1e-12
    )
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def sequence_figures(folder: Path, frames: int, preset: str) -> tuple[float, dict[str, float]]:
    """(median over the first `frames` frames of `implied_albedo`, median colour error in
    degrees of each of COLOUR_CHOICES)."""
    truth = json.loads((folder / "lighting_gt.json").read_text())
    seq = open_sequence(folder, use_poses=True, max_frames=frames)
    pipeline = Pipeline(Config.from_preset(preset, estimate_rgb=True), seq.camera)
    fitted_rgb: list[np.ndarray] = []
    original = pipeline.light.estimate

    def recording_estimate(samples, color_linear, *args, **kwargs):
        fitted_rgb.append(color_linear[samples.pixel_v, samples.pixel_u].mean(axis=0))
        return original(samples, color_linear, *args, **kwargs)

    pipeline.light.estimate = recording_estimate
    values, colour = [], {k: [] for k in COLOUR_CHOICES}
    for index, frame in enumerate(seq.frames):
        result = pipeline.process(frame)
        f = truth["frames"][index]
        l_gt = sh.toggle_condon_shortley(np.asarray(f["sh_lum_world"])) * truth["exposure_scale"]
        forward = result.pose[:3, :3] @ np.array([0.0, 0.0, 1.0])
        values.append(implied_albedo(np.asarray(result.sh) * math.pi, l_gt, forward))
        rgb = f["sh_rgb_world"]
        true_rgb = np.maximum(
            np.asarray(json.loads(rgb) if isinstance(rgb, str) else rgb, np.float64)[:, 0], 0.0
        )
        grey_world = (
            fitted_rgb[-1] / max(float(LUMA @ fitted_rgb[-1]), 1e-12) if fitted_rgb else np.ones(3)
        )
        for name, est in zip(
            COLOUR_CHOICES,
            (np.ones(3), luminance_light_rgb(result.sh_rgb), grey_world),
            strict=True,
        ):
            colour[name].append(colour_error_deg(est, true_rgb))
    return float(np.median(values)), {k: float(np.median(v)) for k, v in colour.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "sequences",
        nargs="*",
        type=Path,
        help="sequence folders with lighting_gt.json (default: all shared)",
    )
    parser.add_argument("--frames", type=int, default=8, help="frames per sequence")
    parser.add_argument("--preset", default="full", help="pipeline preset")
    args = parser.parse_args(argv)
    configure_process()
    folders = args.sequences or sorted(p.parent for p in DATA.glob("*/lighting_gt.json"))
    if not folders:
        print(f"no ground-truth sequences (looked in {DATA})", file=sys.stderr)
        return 2
    rho, colour = {}, {}
    for folder in folders:
        rho[folder.name], colour[folder.name] = sequence_figures(folder, args.frames, args.preset)
        print(
            f"{folder.name:40s} implied albedo {rho[folder.name]:.3f}   colour error "
            + "  ".join(f"{k} {v:.1f}" for k, v in colour[folder.name].items()),
            flush=True,
        )
    values = np.array(list(rho.values()))
    loo = [float(np.median(np.delete(values, i))) for i in range(len(values))]
    print(
        f"median over {len(values)} sequences: {np.median(values):.3f} "
        f"(leave one sequence out: {min(loo):.3f} .. {max(loo):.3f}; "
        f"spread over sequences {values.min():.3f} .. {values.max():.3f})"
    )
    print(
        "light colour error, degrees, median over sequences: "
        + "  ".join(f"{k} {np.median([c[k] for c in colour.values()]):.1f}" for k in COLOUR_CHOICES)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
