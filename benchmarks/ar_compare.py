"""Compare `ar_truth.py` reports of the same AR pairs: PSNR medians and paired differences.

    python benchmarks/ar_compare.py BASE/report.json NEW/report.json [MORE/report.json ...]
        [--lights gt_light estimated] [--changed DB]

Per report: the median over pairs of the PSNR (dB) with each light of --lights (default the
ground-truth light, "gt_light": the rendering's own error, and the estimated light; also
"gt_sun", "gt_full", "paste", "input"), in the affected region, on the shadow pixels and on
the virtual objects, and the median Rendering milliseconds; then, for every report after the
first, the median and the 10th percentile of its per-pair difference from the first (the
pairs matched by sequence and frame). --changed DB lists the pairs whose affected region
moved by more than DB under the first light.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

LIGHTS = ("input", "estimated", "gt_light", "gt_sun", "gt_full", "paste")
REGIONS = ("affected", "shadow", "virtual")


def columns(lights: list[str]) -> list[str]:
    """The report fields of the lights' PSNR in every region."""
    return [f"{light}_psnr_{region}" for light in lights for region in REGIONS]


COLUMNS = columns(["gt_light", "estimated"])


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
    parser.add_argument(
        "--lights",
        nargs="+",
        choices=LIGHTS,
        default=["gt_light", "estimated"],
        help="the lights whose PSNR to compare (default gt_light estimated)",
    )
    parser.add_argument(
        "--changed",
        type=float,
        metavar="DB",
        help="list the pairs whose affected region moved by more than DB (first light)",
    )
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
    wanted = columns(args.lights)
    for path, rep in zip(args.reports, loaded, strict=True):
        missing = [c for c in wanted if c not in rep[pairs[0]]]
        if missing:
            parser.error(f"--lights: {path} has no {', '.join(missing)} (an older ar_truth.py)")
    names = [c.replace("_psnr_", " ") for c in wanted]
    print(f"{len(pairs)} pairs; PSNR dB, median over pairs")
    print("| report | " + " | ".join(names) + " | Rendering ms |")
    print("|---" * (len(wanted) + 2) + "|")
    base = loaded[0]
    for path, rep in zip(args.reports, loaded, strict=True):
        cells = [np.median([rep[p][c] for p in pairs]) for c in wanted]
        ms = np.median([rep[p]["rendering_ms"] for p in pairs])
        print(f"| {path} | " + " | ".join(f"{v:.2f}" for v in cells) + f" | {ms:.0f} |")
        if rep is base:
            continue
        diff = [np.array([rep[p][c] - base[p][c] for p in pairs]) for c in wanted]
        print(
            "| - first: median / p10 | "
            + " | ".join(f"{np.median(d):+.2f} / {np.percentile(d, 10):+.2f}" for d in diff)
            + " | |"
        )
    if args.changed is not None:
        field = wanted[0]
        for path, rep in zip(args.reports[1:], loaded[1:], strict=True):
            print(f"\npairs whose {field} moved by more than {args.changed:g} dB in {path}:")
            for p in pairs:
                before, after = base[p][field], rep[p][field]
                if abs(after - before) > args.changed:
                    print(f"  {p[0]} {p[1]} frame {p[2]}: {before:.2f} -> {after:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
