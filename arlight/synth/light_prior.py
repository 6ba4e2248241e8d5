"""Learn the light prior's per-map moments from HDR maps (pipeline/light_prior_maps.json).

    python -m arlight.synth.light_prior [--maps-dir ../shared/data/hdri] [--out FILE]

For each map: the SH (bands 0..3, arlight's basis, +y up) of the light a scene on a ground
receives (the upper hemisphere, and below the horizon the glow of a ground of albedo 0.3
lit by it), divided by band 0, at 36 headings about +y; their mean and second moment.
The file lists the maps that went in; pipeline.light_prior pools them (leaving maps out).
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
from arlight.synth import environment as env

HEADINGS = 36
GROUND_ALBEDO = 0.3
OUT = Path(__file__).resolve().parents[2] / "pipeline" / "light_prior_maps.json"


def received_light_sh(radiance: np.ndarray) -> np.ndarray:
    """(16,) luminance SH of the map's upper hemisphere plus a lit ground's glow below."""
    h, w = radiance.shape[:2]
    dirs, solid = env.texel_directions(h, w)
    d = dirs.reshape(-1, 3)
    weights = np.repeat(solid, w)
    lum = radiance.reshape(-1, 3).astype(np.float64) @ LUMA
    upper = d[:, 1] > 0
    e_up = float(np.sum(lum[upper] * d[upper, 1] * weights[upper]))  # irradiance, up-facing
    glow = GROUND_ALBEDO / math.pi * e_up
    values = np.where(upper, lum, glow)
    return sh.project_samples(d, values, weights, 4)


def map_moments(radiance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = received_light_sh(radiance)
    samples = []
    for k in range(HEADINGS):
        rotated = sh.rotate(c, env.rotation_y(360.0 * k / HEADINGS))
        samples.append(rotated / rotated[0])
    x = np.stack(samples)
    return x.mean(axis=0), x.T @ x / len(x)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--maps-dir", default="../shared/data/hdri", metavar="DIR")
    parser.add_argument("--out", default=str(OUT), metavar="FILE")
    args = parser.parse_args(argv)
    files = sorted(Path(args.maps_dir).glob("*.hdr"))
    if not files:
        print(f"no .hdr maps in {args.maps_dir} (give --maps-dir)", file=sys.stderr)
        return 2
    maps = {}
    for f in files:
        try:
            radiance = env.load_map(f)
        except env.MapError as exc:
            print(str(exc).replace("--map", "map"), file=sys.stderr)
            return 2
        mean, second = map_moments(radiance)
        maps[f.stem] = {
            "mean": np.round(mean, 7).tolist(),
            "second_moment": np.round(second, 7).tolist(),
        }
        first = sh.dominant_direction(received_light_sh(radiance))
        print(
            f"{f.stem}: light {math.degrees(math.asin(first[1])):.0f} deg above the "
            f"horizon, band 1 / band 0 {np.linalg.norm(mean[1:4]):.2f} (over headings)",
            file=sys.stderr,
        )
    doc = {
        "description": "Per-map moments of the received light's SH / band 0 (bands 0..3, "
        "arlight basis, +y up, 36 headings about +y); pooled by "
        "pipeline/light_prior.py",
        "made_by": "python -m arlight.synth.light_prior",
        "headings": HEADINGS,
        "ground_albedo": GROUND_ALBEDO,
        "maps": maps,
    }
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out} ({len(maps)} maps)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
