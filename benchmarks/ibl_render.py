"""Glossy reflection against a brute-force reference, and render milliseconds per frame.

Part 1, accuracy (--skip-accuracy leaves it out): for every Radiance .hdr map in --hdri
(default ../shared/data/hdri, 6 Poly Haven 1k maps), the glossy lookup of
``pipeline/glossy.py`` (mip pyramid, 6 rings x 6 samples, trilinear) against the same Phong
lobe integrated over every pixel of the full-resolution map (``glossy.glossy_brute_force``),
luminance, per roughness:
- spread: median over --directions Fibonacci directions of |G / G_ref - 1| (per map; the
  table gives the median and the largest over the maps);
- near peak: sum |G - G_ref| / sum G_ref over 16 directions within about 3 degrees of the
  map's brightest pixel (where a sparse pattern meets a small, very bright source);
- mirror lookup: the spread error of one level-0 lookup in the mirror direction (what the
  lobe changes).

Part 2, speed: the built-in scene's 5 objects (pipeline/ibl_render.py `demo_scene`) at
1280 x 720, all of one material (diffuse / glossy roughness 0.2 / mirror) and the mixed demo,
mono and stereo (2 x 1182 x 1464, the paper's Oculus DK2), lit by an LDR frame of the first
map (key 0.18, upsampled to --pano-width, 2048 by default: the paper's video sizes) through
the `boost` operator. Per frame: a new frame's light, then the render (background + shading
+ composite) of every view, with the mip pyramid and the prefiltered glossy maps made in it
where the scene needs them ("pyramid": the pyramid timed alone; "render": the rest); the
views' G-buffers (Open3D ray casting) are made once while the camera and the objects stay
still and are timed apart (a head-tracked view pays them every frame). Median of --repeats
after one warm-up, with the interquartile range; against the paper's 500 Hz (2 ms, GTX 980,
mono 1280 x 720) and 75 Hz (13.3 ms, GTX 690, stereo).

    OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/ibl_render.py \\
        [--hdri DIR] [--directions 256] [--repeats 5] [--pano-width 2048] \\
        [--skip-accuracy] [--backend cpu|cuda] [--out ibl_render.json]

Prints markdown tables; --out writes every number as JSON (with the commit and machine).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import time
from pathlib import Path

import cv2
import numba
import numpy as np

from arlight.pipeline import equirect, glossy, ibl_render
from arlight.pipeline.color import LUMA
from arlight.pipeline.ibl import lighting_from_hdr
from arlight.pipeline.inverse_tone import expand
from arlight.pipeline.virtual_scene import Material, VirtualScene
from arlight.sources.panorama import read_panorama_image
from arlight.sources.synthetic_panorama import ldr_frame, synthetic_sky

ROOT = Path(__file__).resolve().parents[1]
ROUGHNESS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5)
PAPER_MONO_MS = 2.0  # 500 Hz on a GTX 980, 1280 x 720
PAPER_STEREO_MS = 1000.0 / 75.0  # 75 Hz on a GTX 690, 2 x 1182 x 1464


def fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - y * y)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)


def peak_directions(hdr: np.ndarray, n: int = 16) -> np.ndarray:
    lum = hdr @ LUMA.astype(np.float32)
    i, j = np.unravel_index(int(np.argmax(lum)), lum.shape)
    peak = equirect.pixel_directions(*lum.shape)[i, j]
    d = peak + 0.05 * np.random.default_rng(1).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def accuracy(maps: dict[str, np.ndarray], n_dirs: int) -> dict:
    out: dict = {}
    for name, hdr in maps.items():
        pyr = glossy.mip_pyramid(hdr)
        spread, near = fibonacci_directions(n_dirs), peak_directions(hdr)
        per: dict = {}
        for rho in ROUGHNESS:
            ref_s = glossy.glossy_brute_force(hdr, spread, rho) @ LUMA
            ref_p = glossy.glossy_brute_force(hdr, near, rho) @ LUMA
            got_s = glossy.glossy(pyr, spread, rho) @ LUMA
            got_p = glossy.glossy(pyr, near, rho) @ LUMA
            plain = glossy.mirror(pyr, spread) @ LUMA
            per[str(rho)] = {
                "spread": float(np.median(np.abs(got_s / ref_s - 1.0))),
                "near_peak": float(np.abs(got_p - ref_p).sum() / ref_p.sum()),
                "mirror_lookup": float(np.median(np.abs(plain / ref_s - 1.0))),
            }
        out[name] = per
        print(f"  {name}: done", flush=True)
    return out


def print_accuracy(acc: dict) -> None:
    print(
        "\n| roughness | lobe radius (deg) | spread: median / max over maps | near peak: "
        "median / max | mirror lookup instead: median |"
    )
    print("|---|---|---|---|---|")
    for rho in ROUGHNESS:
        rows = [acc[m][str(rho)] for m in acc]
        s = [r["spread"] for r in rows]
        p = [r["near_peak"] for r in rows]
        mirror = [r["mirror_lookup"] for r in rows]
        radius = math.degrees(glossy.lobe_radius_rad(glossy.phong_exponent(rho)))
        print(
            f"| {rho} | {radius:.2f} | {100 * np.median(s):.1f} % / {100 * max(s):.1f} % | "
            f"{100 * np.median(p):.1f} % / {100 * max(p):.1f} % | "
            f"{100 * np.median(mirror):.1f} % |"
        )
    print("\nper map, spread / near peak (%):")
    for m in acc:
        cells = " ".join(
            f"{rho}: {100 * acc[m][str(rho)]['spread']:.1f}/"
            f"{100 * acc[m][str(rho)]['near_peak']:.0f}"
            for rho in ROUGHNESS
        )
        print(f"  {m}: {cells}")


def scene_of(material: Material | None) -> VirtualScene:
    """The demo's 5 objects, all of `material` (None: the mixed demo)."""
    demo = ibl_render.demo_scene()
    if material is None:
        return demo
    import dataclasses

    return VirtualScene(tuple(dataclasses.replace(o, material=material) for o in demo.objects))


def timed(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up (compilation, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    q1, med, q3 = np.percentile(times, [25, 50, 75])
    return float(med), float(q3 - q1)


def speed(hdr_map: np.ndarray, pano_width: int, repeats: int, backend: str) -> list[dict]:
    ldr = ldr_frame(hdr_map, 0.18)
    ldr = cv2.resize(ldr, (pano_width, pano_width // 2), interpolation=cv2.INTER_LINEAR)
    hdr = expand(ldr, "boost")
    diffuse = lighting_from_hdr(hdr).diffuse_map
    materials = {
        "diffuse": Material((0.8, 0.8, 0.8)),
        "glossy 0.2": Material((0.9, 0.9, 0.9), 0.2, 1.0),
        "mirror": Material((0.95, 0.95, 0.95), mirror=True),
        "mixed (demo)": None,
    }
    rows = []
    for mode in ("mono", "stereo"):
        size = ibl_render.MONO_SIZE if mode == "mono" else ibl_render.EYE_SIZE
        camera = ibl_render.view_camera(size, 75.0)
        head = ibl_render.look_along([0.0, 0.0, 1.0])
        poses = ibl_render.eye_poses(head) if mode == "stereo" else (head,)
        for label, material in materials.items():
            renderer = ibl_render.IblRenderer(scene_of(material), backend)
            views = [renderer.prepare_view(camera, p) for p in poses]
            gbuffer_ms, _ = timed(
                lambda r=renderer, p=poses, c=camera: [r.prepare_view(c, q) for q in p], repeats
            )
            pyramid_ms, _ = timed(lambda: glossy.mip_pyramid(hdr), repeats)

            def frame(r=renderer, v=views) -> None:
                # a new frame's light: its pyramid and prefiltered maps made in the render,
                # where the scene needs them
                light = ibl_render.frame_light(hdr, diffuse, ldr)
                for x in v:
                    r.render(x, light)

            frame_ms, iqr = timed(frame, repeats)
            # the pyramid is built only for glossy objects (mirrors read the map itself)
            glossy_in_view = any(ibl_render.MODE_GLOSSY in v.modes for v in views)
            render_ms = frame_ms - pyramid_ms if glossy_in_view else frame_ms
            if not glossy_in_view:
                pyramid_ms = 0.0
            paper = PAPER_MONO_MS if mode == "mono" else PAPER_STEREO_MS
            rows.append(
                {
                    "mode": mode,
                    "material": label,
                    "size": f"{size[0]}x{size[1]}" + (" x 2" if mode == "stereo" else ""),
                    "object_pixels": int(sum(len(v.pixels) for v in views)),
                    "gbuffer_ms": gbuffer_ms,
                    "pyramid_ms": pyramid_ms,
                    "render_ms": render_ms,
                    "render_iqr_ms": iqr,
                    "frame_ms": frame_ms,
                    "hz": 1000.0 / frame_ms,
                    "paper_ms": paper,
                    "ratio_to_paper": frame_ms / paper,
                }
            )
            print(f"  {mode} {label}: {frame_ms:.0f} ms", flush=True)
    return rows


def print_speed(rows: list[dict], threads: int, pano_width: int) -> None:
    print(
        f"\nrender ms per frame ({threads} numba CPU thread(s), panorama {pano_width}x"
        f"{pano_width // 2}; median of repeats, IQR in brackets):\n"
    )
    print(
        "| view | material | object px | G-buffer once | pyramid | render | per frame | "
        "Hz | paper | x paper |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['mode']} {r['size']} | {r['material']} | {r['object_pixels']} | "
            f"{r['gbuffer_ms']:.0f} | {r['pyramid_ms']:.0f} | {r['render_ms']:.0f} "
            f"({r['render_iqr_ms']:.0f}) | {r['frame_ms']:.0f} | {r['hz']:.1f} | "
            f"{r['paper_ms']:.1f} ms ({1000 / r['paper_ms']:.0f} Hz) | "
            f"{r['ratio_to_paper']:.0f} |"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hdri", type=Path, default=ROOT.parent / "shared" / "data" / "hdri")
    ap.add_argument("--directions", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--pano-width", type=int, default=2048)
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument(
        "--backend",
        choices=glossy.BACKENDS,
        default="cpu",
        help="the mirror / glossy lookups on the CPU or, where numba.cuda sees a "
        "GPU, in CUDA (each call copies the pyramid and the pixels to the "
        "device and back: timed as such)",
    )
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    files = sorted(args.hdri.glob("*.hdr")) if args.hdri.is_dir() else []
    maps = {f.stem: read_panorama_image(f) for f in files}
    if not maps:
        print(f"no .hdr maps in {args.hdri}: the built-in sky only")
        maps = {"built-in sky": synthetic_sky(1024)}
    report: dict = {}
    if not args.skip_accuracy:
        print(f"glossy vs brute force over {len(maps)} maps, {args.directions} directions:")
        report["accuracy"] = accuracy(maps, args.directions)
        print_accuracy(report["accuracy"])
    threads = numba.get_num_threads()
    print(f"\nspeed (lit by {next(iter(maps))}):")
    report["speed"] = speed(next(iter(maps.values())), args.pano_width, args.repeats, args.backend)
    print_speed(report["speed"], threads, args.pano_width)
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    report.update(
        {
            "benchmark": "ibl_render",
            "commit": commit,
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "numba_threads": threads,
            "python": platform.python_version(),
            "repeats": args.repeats,
            "backend": args.backend,
        }
    )
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
