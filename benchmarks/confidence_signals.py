"""How well per-frame signals rank the light's error: Spearman over recorded fits.

    python benchmarks/confidence_signals.py CACHE [CACHE ...]

Each CACHE is a `benchmarks/light_replay.py record` folder. The fit is replayed with the
recorded configuration. For each frame the raw error is the angle from the reported
direction (above the support plane's horizon) to the upper-hemisphere truth. It is ranked
against the confidence and its evidence: the normals' spread, the horizon disagreement, the
condition number, the fit's relative residual, and how directional the light came out
(|band 1| / band 0). Spearman per cache and pooled; a good confidence is strongly negative.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from arlight.pipeline.config import Config

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run as a script
from benchmarks.light_replay import _error, estimate_recorded  # noqa: E402

SIGNALS = ("confidence", "directional", "spread", "horizon", "condition", "residual")


def frame_signals(cache: Path) -> list[dict]:
    """One row per recorded frame: its raw error (degrees) and the signals."""
    base = json.loads((cache / "config.json").read_text())
    params = Config.from_preset(base["preset"], **base["overrides"]).estimation
    rows = []
    for file in sorted(cache.glob("*.npz")):
        data = np.load(file)
        up_seen = None
        for i, m in enumerate(json.loads(str(data["meta"]))):
            up = None if m["up"] is None else np.asarray(m["up"])
            est = estimate_recorded(data, i, m, params)
            up_seen = up if up is not None else up_seen
            truth = np.asarray(m["truth_upper_camera"])
            c = est.confidence
            rows.append(
                {
                    "cache": cache.name,
                    "error": _error(est.sh, up_seen, np.asarray(m["pose"])[:3, :3], truth),
                    "confidence": c.value,
                    "directional": float(np.linalg.norm(est.sh[1:4]) / max(est.sh[0], 1e-9)),
                    "spread": c.normal_spread,
                    "horizon": c.horizon_disagreement_deg,
                    "condition": c.condition_number,
                    "residual": est.residual_rel,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("caches", nargs="+", type=Path, help="light_replay.py record folders")
    args = parser.parse_args(argv)
    rows = [row for cache in args.caches for row in frame_signals(cache)]
    groups = [(c.name, [r for r in rows if r["cache"] == c.name]) for c in args.caches]
    groups.append(("pooled", rows))
    print("| signal | " + " | ".join(f"{name} ({len(g)} frames)" for name, g in groups) + " |")
    print("|---" * (len(groups) + 1) + "|")
    for key in SIGNALS:
        rhos = [
            spearmanr([r[key] for r in g], [r["error"] for r in g]).statistic for _, g in groups
        ]
        print(f"| {key} | " + " | ".join(f"{rho:+.2f}" for rho in rhos) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
