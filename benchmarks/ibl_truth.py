"""The 360-degree lighting path against HDR truth: LDR frames made from real HDR maps.

For every Radiance .hdr map in --hdri (default ../shared/data/hdri, 6 Poly Haven 1k maps)
the truth is computed from the HDR map itself at full resolution (arlight/ibl_evaluation.py:
luminance SH, dominant direction = first moment, irradiance at 2048 normals over the whole
sphere by brute force). LDR frames are made as a camera records them
(sources/synthetic_panorama.py `ldr_frame`: exposure keyed so that the solid-angle-weighted
median luminance maps to --keys 0.09 0.18 0.36, clipping, sRGB, 8 bits) and run through the
path (pipeline/ibl.py, default parameters: SH from the map area-averaged to 128x64, a 32x16
diffuse map by brute force) with every inverse tone-mapping operator. Per map, key and
operator:

- angle (degrees) between the recovered and the true dominant direction (recovered:
  sh.dominant_direction of the recovered SH; the brightest-region comparator
  `brightest_direction` is reported in the summary);
- irradiance error: mean relative error of the diffuse irradiance over the 2048 normals,
  the 32x16 diffuse map looked up bilinearly (as a renderer does), after the best single
  scale factor;
- SH error: relative L2 of the 16 luminance coefficients after the same scale.

Also, per map: a short video (--video-frames frames, the map turning about +y by 360 /
frames degrees per frame, key 0.18) written with cv2.VideoWriter (mp4v) and read back
through `open_panorama` (decode thread), against the same frames without the codec; and the
diffuse map's own error and milliseconds at 32x16, 64x32 and 128x64 (brute force over the
HDR map area-averaged to the same size) and of the SH path, against the full-resolution
brute-force reference (no tone mapping: the error of the resolution alone). --boost-sweep
adds the `boost` operator's factor against the numbers, with a leave-one-map-out choice.

    OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/ibl_truth.py \\
        [--hdri DIR] [--keys 0.09 0.18 0.36] [--video-frames 8] [--repeats 20] \\
        [--boost-sweep] [--out ibl_truth.json]

Prints markdown tables; --out writes every number as JSON (with the commit and machine).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from arlight.ibl_evaluation import (
    HdrTruth,
    best_scale,
    diffuse_map_at,
    hdr_truth,
    irradiance_at,
    relative_irradiance_error,
    sh_error,
)
from arlight.pipeline import equirect, sh
from arlight.pipeline.color import LUMA
from arlight.pipeline.ibl import (
    IblParams,
    angle_deg,
    brightest_direction,
    diffuse_map_brute_force,
    diffuse_map_sh,
    lighting_from_hdr,
    radiance_sh,
)
from arlight.pipeline.inverse_tone import DEFAULT_OPERATOR, OPERATORS, boost_saturated, expand
from arlight.sources.panorama import open_panorama, read_panorama_image
from arlight.sources.synthetic_panorama import keyed_exposure, ldr_frame

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_HDRI = ROOT.parent / "shared" / "data" / "hdri"
SIZES = ((32, 16), (64, 32), (128, 64))
BOOSTS = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)


def score(hdr: np.ndarray, truth: HdrTruth, params: IblParams) -> dict:
    """The three metrics (plus the comparators) of one HDR map recovered from an LDR frame."""
    result = lighting_from_hdr(hdr, params)
    estimate = diffuse_map_at(result.diffuse_map, truth.normals)
    scale = best_scale(estimate, truth.irradiance)
    irr_sh = sh.evaluate(sh.irradiance_from_radiance(result.sh), truth.normals)
    return {
        "angle_deg": angle_deg(result.dominant_direction, truth.dominant_direction),
        "angle_brightest_deg": angle_deg(brightest_direction(hdr), truth.dominant_direction),
        "irradiance_error": relative_irradiance_error(estimate, truth.irradiance, scale),
        "irradiance_error_sh": relative_irradiance_error(irr_sh, truth.irradiance),
        "sh_error": sh_error(result.sh, truth.sh, scale),
        "timings_ms": result.timings_ms,
    }


def run_operators(name: str, hdr: np.ndarray, truth: HdrTruth, keys: list[float]) -> dict:
    out = {}
    for key in keys:
        ldr = ldr_frame(hdr, key)
        clipped = float(
            (equirect.pixel_solid_angles(*ldr.shape[:2]) * (ldr.max(axis=-1) >= 255)).sum()
            / (4 * math.pi)
        )
        row = {"clipped_fraction": clipped}
        for op in OPERATORS:
            t0 = time.perf_counter()
            expanded = expand(ldr, op)
            ms = (time.perf_counter() - t0) * 1e3
            row[op] = score(expanded, truth, IblParams(operator=op))
            row[op]["timings_ms"] = {"InverseTone": ms, **row[op]["timings_ms"]}
        out[str(key)] = row
    return out


def run_video(
    name: str, hdr: np.ndarray, truth: HdrTruth, frames: int, key: float, folder: Path
) -> dict:
    """The map turning about +y, through mp4v and the decode thread, vs the same LDR frames."""
    h, w = hdr.shape[:2]
    exposure = keyed_exposure(hdr, key)
    shifts = [round(i * w / frames) for i in range(frames)]
    ldrs = [
        ldr_frame(equirect.rotate_about_y(hdr, 2 * math.pi * s / w), exposure=exposure)
        for s in shifts
    ]
    path = folder / f"{name}.mp4"
    fps = 24.0
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        raise RuntimeError("cv2.VideoWriter cannot write mp4v here")
    for ldr in ldrs:
        writer.write(np.ascontiguousarray(ldr[..., ::-1]))
    writer.release()
    params = IblParams(operator=DEFAULT_OPERATOR)
    rows = {"video": [], "direct": []}
    timestamps = []
    with open_panorama(path) as source:
        for i, (t, image) in enumerate(source):
            timestamps.append(t)
            truth_i = truth.rotated_about_y(shifts[i], w)
            rows["video"].append(score(expand(image, params.operator), truth_i, params))
            rows["direct"].append(score(expand(ldrs[i], params.operator), truth_i, params))
        decode_ms = float(np.median(source.decode_ms))
        wait_ms = float(np.median(source.wait_ms))
    summary = {}
    for kind, r in rows.items():
        summary[kind] = {
            k: float(np.median([x[k] for x in r]))
            for k in ("angle_deg", "irradiance_error", "sh_error")
        }
    summary["frames_read"] = len(rows["video"])
    summary["timestamps_s"] = timestamps
    summary["timestamps_ok"] = bool(
        np.allclose(timestamps, np.arange(len(timestamps)) / fps, atol=1e-3)
    )
    summary["decode_ms"] = decode_ms
    summary["wait_ms"] = wait_ms
    summary["bytes"] = path.stat().st_size
    return summary


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up: caches (kernels, bases)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def run_sizes(hdr: np.ndarray, truth: HdrTruth, repeats: int) -> dict:
    """The diffuse map's error from its resolution alone, and its milliseconds."""
    lum = np.asarray(hdr, dtype=np.float32) @ LUMA.astype(np.float32)
    out = {}
    for size in SIZES:
        small = equirect.downsample(hdr, *size)
        dmap = diffuse_map_brute_force(small, size, size)
        est = diffuse_map_at(dmap, truth.normals)
        err = np.abs(est - truth.irradiance) / truth.irradiance
        out[f"{size[0]}x{size[1]}"] = {
            "error_mean": float(err.mean()),
            "error_max": float(err.max()),
            "downsample_ms": _median_ms(lambda s=size: equirect.downsample(hdr, *s), repeats),
            "brute_force_ms": _median_ms(
                lambda s=size, m=small: diffuse_map_brute_force(m, s, s), repeats
            ),
        }

    def sh_path():
        c = radiance_sh(equirect.downsample(hdr, 128, 64))
        return diffuse_map_sh(c, (32, 16)), c

    dmap, c = sh_path()
    est = diffuse_map_at(dmap, truth.normals)
    exact = sh.evaluate(sh.irradiance_from_radiance(LUMA @ c), truth.normals)
    out["sh"] = {
        "error_mean": float(np.mean(np.abs(est - truth.irradiance) / truth.irradiance)),
        "error_max": float(np.max(np.abs(est - truth.irradiance) / truth.irradiance)),
        "error_mean_exact_eval": float(
            np.mean(np.abs(exact - truth.irradiance) / truth.irradiance)
        ),
        "ms": _median_ms(sh_path, repeats),
    }
    small = equirect.downsample(hdr, 128, 64)
    out["sh"]["project_ms"] = _median_ms(lambda: radiance_sh(small), repeats)
    # the reference itself at the 32x16 pixel directions, for its cost
    normals = equirect.pixel_directions(16, 32).reshape(-1, 3)
    out["reference_32x16_ms"] = _median_ms(lambda: irradiance_at(lum, normals), 2)
    return out


def run_boost_sweep(maps: dict, truths: dict, keys: list[float]) -> dict:
    """`boost` with each factor in BOOSTS: per key the medians over the maps, and a
    leave-one-map-out choice (the factor best on the other maps' median irradiance error at
    key 0.18, then scored on the map left out)."""
    per = {}  # (boost, key) -> {map: score}
    for b in BOOSTS:
        for key in keys:
            per[(b, key)] = {}
            for name, hdr in maps.items():
                ldr = ldr_frame(hdr, key)
                per[(b, key)][name] = score(boost_saturated(ldr, b), truths[name], IblParams())
    table = {
        str(b): {
            str(k): {
                m: float(np.median([v[m] for v in per[(b, k)].values()]))
                for m in ("angle_deg", "irradiance_error")
            }
            for k in keys
        }
        for b in BOOSTS
    }
    loo = {}
    key = 0.18 if 0.18 in keys else keys[len(keys) // 2]
    for held in maps:
        others = [n for n in maps if n != held]
        chosen = min(
            BOOSTS, key=lambda b: np.median([per[(b, key)][n]["irradiance_error"] for n in others])
        )
        loo[held] = {
            "boost": chosen,
            **{m: per[(chosen, key)][held][m] for m in ("angle_deg", "irradiance_error")},
        }
    return {"medians": table, "leave_one_out": loo, "key": key}


# --------------------------------------------------------------------------- tables


def _f(v: float, spec: str = ".1f") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def print_tables(report: dict, keys: list[float]) -> None:
    ops = list(OPERATORS)
    maps = report["maps"]
    print("### Per map and exposure: angle (deg) / irradiance error (%) / SH error\n")
    print("| map | key | clipped | " + " | ".join(ops) + " |")
    print("| --- | --- | --- | " + " | ".join("---" for _ in ops) + " |")
    for name, m in maps.items():
        for key in keys:
            row = m["operators"][str(key)]
            cells = [
                f"{_f(row[o]['angle_deg'])} / {_f(100 * row[o]['irradiance_error'], '.0f')}"
                f" / {_f(row[o]['sh_error'], '.2f')}"
                for o in ops
            ]
            print(
                f"| {name} | {key} | {100 * row['clipped_fraction']:.0f} % | "
                + " | ".join(cells)
                + " |"
            )
    print("\n### Median over the maps: angle (deg) / irradiance error (%) / SH error\n")
    print(
        "| key | " + " | ".join(ops) + " | default, brightest-region direction (deg) | "
        "default, SH-irradiance error (%) |"
    )
    print("| --- | " + " | ".join("---" for _ in ops) + " | --- | --- |")
    for key in keys:
        cells = []
        for o in ops:
            vals = [m["operators"][str(key)][o] for m in maps.values()]
            cells.append(
                f"{np.median([v['angle_deg'] for v in vals]):.1f} / "
                f"{100 * np.median([v['irradiance_error'] for v in vals]):.0f} / "
                f"{np.median([v['sh_error'] for v in vals]):.2f}"
            )
        d = [m["operators"][str(key)][DEFAULT_OPERATOR] for m in maps.values()]
        print(
            f"| {key} | "
            + " | ".join(cells)
            + f" | {np.median([v['angle_brightest_deg'] for v in d]):.1f}"
            + f" | {100 * np.median([v['irradiance_error_sh'] for v in d]):.0f} |"
        )
    if any("video" in m for m in maps.values()):
        print(
            f"\n### Video (map turning about +y, key 0.18, {DEFAULT_OPERATOR}): median over "
            "its frames, angle (deg) / irradiance error (%) / SH error\n"
        )
        print(
            "| map | frames read | timestamps | mp4v + decode thread | same frames, no codec "
            "| decode ms/frame (own thread) | processing waited ms/frame | video KiB |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for name, m in maps.items():
            v = m["video"]
            cells = [
                f"{v[k]['angle_deg']:.1f} / {100 * v[k]['irradiance_error']:.0f} / "
                f"{v[k]['sh_error']:.2f}"
                for k in ("video", "direct")
            ]
            print(
                f"| {name} | {v['frames_read']} | {'ok' if v['timestamps_ok'] else 'WRONG'} | "
                + " | ".join(cells)
                + f" | {v['decode_ms']:.1f} | {v['wait_ms']:.1f} | "
                f"{v['bytes'] / 1024:.0f} |"
            )
        videos = [m["video"] for m in maps.values()]
        cells = [
            f"{np.median([v[k]['angle_deg'] for v in videos]):.1f} / "
            f"{100 * np.median([v[k]['irradiance_error'] for v in videos]):.0f} / "
            f"{np.median([v[k]['sh_error'] for v in videos]):.2f}"
            for k in ("video", "direct")
        ]
        print("| median over the maps | | | " + " | ".join(cells) + " | | | |")
    print(
        "\n### Diffuse map resolution against the full-resolution brute-force reference "
        "(HDR maps, no tone mapping)\n"
    )
    print(
        "| method | mean relative error (median over maps) | worst map's max error | "
        "ms: downsample + integrate (median over maps) |"
    )
    print("| --- | --- | --- | --- |")
    sizes = [m["sizes"] for m in maps.values()]
    for w, h in SIZES:
        k = f"{w}x{h}"
        print(
            f"| brute force {k} (source {k}) | "
            f"{100 * np.median([s[k]['error_mean'] for s in sizes]):.2f} % | "
            f"{100 * np.max([s[k]['error_max'] for s in sizes]):.1f} % | "
            f"{np.median([s[k]['downsample_ms'] for s in sizes]):.2f} + "
            f"{np.median([s[k]['brute_force_ms'] for s in sizes]):.2f} |"
        )
    exact = np.median([s["sh"]["error_mean_exact_eval"] for s in sizes])
    print(
        f"| SH (bands 0-3 from 128x64) -> 32x16 map | "
        f"{100 * np.median([s['sh']['error_mean'] for s in sizes]):.2f} % (evaluated exactly "
        f"at the normals: {100 * exact:.2f} %) | "
        f"{100 * np.max([s['sh']['error_max'] for s in sizes]):.1f} % | "
        f"{np.median([s['sh']['ms'] for s in sizes]):.2f} in all (projection "
        f"{np.median([s['sh']['project_ms'] for s in sizes]):.2f}) |"
    )
    print(
        f"| reference: every pixel of the 1024x512 map -> 32x16 | 0 | 0 | "
        f"{np.median([s['reference_32x16_ms'] for s in sizes]):.0f} |"
    )
    sweep = report.get("boost_sweep")
    if sweep:
        print("\n### `boost` factor: median over the maps, angle (deg) / irradiance error (%)\n")
        print("| boost | " + " | ".join(f"key {k}" for k in keys) + " |")
        print("| --- | " + " | ".join("---" for _ in keys) + " |")
        for b, row in sweep["medians"].items():
            print(
                f"| {b} | "
                + " | ".join(
                    f"{row[str(k)]['angle_deg']:.1f} / {100 * row[str(k)]['irradiance_error']:.0f}"
                    for k in keys
                )
                + " |"
            )
        loo = sweep["leave_one_out"]
        print(
            f"\nLeave one map out (factor chosen on the other maps' median irradiance error at "
            f"key {sweep['key']}): "
            + ", ".join(f"{n} {v['boost']:g}" for n, v in loo.items())
            + f"; held-out median {np.median([v['angle_deg'] for v in loo.values()]):.1f} deg / "
            f"{100 * np.median([v['irradiance_error'] for v in loo.values()]):.0f} %"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--hdri",
        type=Path,
        default=DEFAULT_HDRI,
        help=f"folder of .hdr maps (default {DEFAULT_HDRI})",
    )
    parser.add_argument("--keys", type=float, nargs="+", default=[0.09, 0.18, 0.36])
    parser.add_argument(
        "--video-frames", type=int, default=8, help="frames of each rotating video (0: no video)"
    )
    parser.add_argument("--repeats", type=int, default=20, help="timed repeats per size")
    parser.add_argument(
        "--boost-sweep",
        action="store_true",
        help="also sweep the boost factor, with a leave-one-map-out choice",
    )
    parser.add_argument("--out", type=Path, help="write all numbers as JSON")
    args = parser.parse_args(argv)
    files = sorted(args.hdri.glob("*.hdr"))
    if not files:
        print(
            f"ibl_truth: no .hdr maps in {args.hdri} (the shared data is absent?)", file=sys.stderr
        )
        return 2
    t_start = time.perf_counter()
    maps, truths, report = {}, {}, {"maps": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            name = f.name.removesuffix("_1k.hdr").removesuffix(".hdr")
            t0 = time.perf_counter()
            hdr = read_panorama_image(f)
            truth = hdr_truth(hdr)
            maps[name], truths[name] = hdr, truth
            entry = {
                "file": f.name,
                "size": [hdr.shape[1], hdr.shape[0]],
                "dominant_direction": truth.dominant_direction.tolist(),
                "operators": run_operators(name, hdr, truth, args.keys),
            }
            if args.video_frames > 0:
                entry["video"] = run_video(name, hdr, truth, args.video_frames, 0.18, Path(tmp))
            entry["sizes"] = run_sizes(hdr, truth, args.repeats)
            report["maps"][name] = entry
            print(
                f"ibl_truth: {name} done in {time.perf_counter() - t0:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    if args.boost_sweep:
        report["boost_sweep"] = run_boost_sweep(maps, truths, args.keys)
    print_tables(report, args.keys)
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False, cwd=ROOT
        ).stdout.strip()
    except OSError:
        commit = "unknown"
    report.update(
        {
            "benchmark": "ibl_truth",
            "commit": commit,
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "opencv": cv2.__version__,
            "numpy": np.__version__,
            "keys": args.keys,
            "default_operator": DEFAULT_OPERATOR,
            "seconds": time.perf_counter() - t_start,
        }
    )
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
        print(f"ibl_truth: wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
