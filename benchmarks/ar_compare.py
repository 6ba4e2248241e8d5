"""Compare `ar_truth.py` reports of the same AR pairs: PSNR medians and paired differences.

    python benchmarks/ar_compare.py BASE/report.json NEW/report.json [MORE/report.json ...]

Per report: the median over pairs of the PSNR (dB) with the ground-truth light ("gt_light":
the rendering's own error) and with the estimated light, in the affected region, on the
shadow pixels and on the virtual objects, and the median Rendering milliseconds; then, for
every report after the first, the median and the 10th percentile of its per-pair difference
from the first (the pairs matched by sequence and frame).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

COLUMNS = [
    f"{light}_psnr_{region}"
    for light in ("gt_light", "estimated")
    for region in ("affected", "shadow", "virtual")
]


def _load(path: str) -> dict[tuple[str, str, int], dict]:
    """The report's rows by (sequence, preset, frame); ValueError naming the file."""
    try:
        with open(path) as f:
            rows = json.load(f)["rows"]
        return {(r["sequence"], r["preset"], r["frame"]): r for r in rows}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not an ar_truth.py report.json ({exc})") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", help="report.json files of ar_truth.py")
    args = parser.parse_args(argv)
    try:
        loaded = [_load(p) for p in args.reports]
    except ValueError as exc:
        parser.error(f"reports: {exc}")
    pairs = sorted(set.intersection(*(set(r) for r in loaded)))
    if not pairs:
        parser.error(
            "the reports share no AR pair (sequence, preset, frame): run them on the same sequences"
        )
    names = [c.replace("_psnr_", " ") for c in COLUMNS]
    print(f"{len(pairs)} pairs; PSNR dB, median over pairs")
    print("| report | " + " | ".join(names) + " | Rendering ms |")
    print("|---" * (len(COLUMNS) + 2) + "|")
    base = loaded[0]
    for path, rep in zip(args.reports, loaded, strict=True):
        cells = [np.median([rep[p][c] for p in pairs]) for c in COLUMNS]
        ms = np.median([rep[p]["rendering_ms"] for p in pairs])
        print(f"| {path} | " + " | ".join(f"{v:.2f}" for v in cells) + f" | {ms:.0f} |")
        if rep is base:
            continue
        diff = [np.array([rep[p][c] - base[p][c] for p in pairs]) for c in COLUMNS]
        print(
            "| - first: median / p10 | "
            + " | ".join(f"{np.median(d):+.2f} / {np.percentile(d, 10):+.2f}" for d in diff)
            + " | |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
