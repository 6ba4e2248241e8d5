"""`ar_truth.py` figures by kind of light and by the virtual sphere's material.

    python benchmarks/ar_by_light.py REPORT.json [--data DIR ...] [--sunny-share 0.3]

Each pair's map and rotation come from its sequence's lighting_gt.json (found under --data,
default: the corpus cache and ../shared/data/synthetic) and its sphere's material from
ar/virtual_scene.json. A pair is "sunny" when the map's brightest compact region
(`arlight.synth.environment.brightest_compact_region`, the truth a compact source is judged
by) carries at least --sunny-share of the irradiance at the ground, else "soft"; a room
(truth_reference "probe") is its own group, since its light is the room's, not the map's.
Prints, per group, the pairs, the maps and the median PSNR (dB) of every variant in the
affected region, on the shadow pixels and on the objects (issue 32: with the true light,
30 dB or more in the affected region on sunny maps as on soft ones).
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

DEFAULT_DATA = [
    Path.home() / ".cache" / "arlight" / "corpus",
    Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic",
]
MAPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "hdri"
VARIANTS = ("estimated", "gt_light", "gt_sun", "gt_full", "paste")
REGIONS = ("affected", "shadow", "virtual")


@functools.lru_cache(maxsize=64)
def compact_share(env_map: str, rotation_deg: float) -> float:
    """Share of the ground's irradiance from the map's brightest compact region."""
    from arlight.synth.environment import brightest_compact_region, load_map

    return float(brightest_compact_region(load_map(MAPS / f"{env_map}.hdr"), rotation_deg).share)


def sphere_material(folder: Path) -> str:
    """The first virtual object's material as the generator names it ("mirror", "glossy0.1",
    "diffuse"; "diffuse" when the file does not say, "unknown" without a readable file)."""
    try:
        info = json.loads((folder / "ar" / "virtual_scene.json").read_text())
    except (OSError, ValueError):
        return "unknown"
    return str(info.get("virtual_material", "diffuse")) if isinstance(info, dict) else "unknown"


@functools.lru_cache(maxsize=64)  # a sequence's pairs share its truth file
def _truth(folder: Path) -> dict:
    return json.loads((folder / "lighting_gt.json").read_text())


def pair_groups(row: dict, folder: Path, sunny_share: float) -> tuple[str, str, str]:
    """(light group, map, material) of one report row."""
    truth = _truth(folder)
    frame = truth["frames"][row["frame"]]
    if truth.get("truth_reference") == "probe":
        light = "room"
    else:
        share = compact_share(frame["env_map"], float(frame["env_rotation_deg"]))
        light = "sunny" if share >= sunny_share else "soft"
    return light, frame["env_map"], sphere_material(folder)


def _find(sequence: str, data: list[Path]) -> Path | None:
    for d in data:
        if (d / sequence / "lighting_gt.json").is_file():
            return d / sequence
    return None


def _median(values: list) -> float:
    """Median of the finite values; nan when there are none."""
    finite = [float(v) for v in values if v is not None and np.isfinite(v)]
    return float(np.median(finite)) if finite else float("nan")


def table(rows: list[dict], key: str) -> str:
    """Markdown: per group (`key` of the annotated rows), pairs, maps and median PSNRs."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        groups[r[key]].append(r)
    variants = [v for v in VARIANTS if any(f"{v}_psnr_affected" in r for r in rows)]
    head = "| " + key + " | pairs | maps | " + " | ".join(variants) + " |"
    lines = [head, "|---|---|---|" + "---|" * len(variants)]
    for name in sorted(groups):
        sel = groups[name]
        cells = []
        for v in variants:
            medians = [_median([r.get(f"{v}_psnr_{region}") for r in sel]) for region in REGIONS]
            cells.append(" / ".join(f"{m:.1f}" for m in medians))
        maps = len({r["map"] for r in sel})
        lines.append(f"| {name} | {len(sel)} | {maps} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="report.json of ar_truth.py")
    parser.add_argument("--data", type=Path, action="append", help="folders of the sequences")
    parser.add_argument(
        "--sunny-share",
        type=float,
        default=0.3,
        help="share of the ground's irradiance from the brightest compact region at and "
        "above which a map counts as sunny (default 0.3)",
    )
    args = parser.parse_args(argv)
    try:
        rows = json.loads(args.report.read_text())["rows"]
        if not all(isinstance(r["sequence"], str) and isinstance(r["frame"], int) for r in rows):
            raise ValueError("a row without its sequence and frame")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"{args.report}: not an ar_truth.py report.json ({exc})", file=sys.stderr)
        return 2
    if not MAPS.is_dir():
        print(f"no HDR maps at {MAPS} (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    data = args.data or DEFAULT_DATA
    annotated = []
    for r in rows:
        folder = _find(r["sequence"], data)
        if folder is None:
            print(
                f"{r['sequence']}: not found under {', '.join(map(str, data))} (--data)",
                file=sys.stderr,
            )
            return 2
        try:
            light, env_map, material = pair_groups(r, folder, args.sunny_share)
        except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
            print(
                f"{folder}: its truth does not describe frame {r['frame']} ({exc})", file=sys.stderr
            )
            return 2
        annotated.append({**r, "light": light, "map": env_map, "material": material})
    print("PSNR (dB) median over pairs, affected / shadow / objects\n")
    print(table(annotated, "light") + "\n")
    print(table(annotated, "material") + "\n")
    no_mirror = [r for r in annotated if r["material"] != "mirror"]
    print("without the mirror spheres:\n")
    print(table(no_mirror, "light"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
