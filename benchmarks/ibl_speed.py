"""The 360 path per frame on the CPU, before and after, alternated in one run (issue 35,
item 4): `arlight ibl --render` at 1280x720 from a 2048x1024 LDR panorama.

Per frame, as `arlight ibl` runs it (``arlight/ibl.py``): the map (``process_frames``:
inverse tone mapping of the full frame, the SH and the 32x16 diffuse map) and the render
(``FrameRenderer.render``: the pyramid and the prefiltered maps where the scene needs them,
the background, the objects' shading, the composite) of the built-in scene's 5 objects, all
of one material (diffuse / glossy roughness 0.2 / mirror) or the mixed demo; the views'
G-buffers are made once (camera and objects still) and not counted. The frames: an LDR
frame of --hdr (key 0.18, resized to --pano-width) turning about +y by 1/--frames of a turn
per frame; the first 2 frames are warm-up (compilation, caches) and left out; median over
the rest.

With --baseline REF the same measurement runs in a git worktree of commit REF (a temporary
copy of the package) and in this tree, in turn (baseline, current, baseline, ...; --rounds
each), every run a fresh process; figures are the medians over the rounds of each run's
median, and the ratio baseline / current per round. The renders of the first frame of both
trees are compared (PSNR over the whole 8-bit image, largest absolute difference).

With --video the whole command is timed too, in the worker's process: `arlight ibl VIDEO
--render DIR --scene glossy.json` (5 spheres of roughness 0.2 where the demo's objects are)
on an mp4v video of the same frames 3 times over (decode thread, processing, render, PNG
writing); ms per frame = (wall time of all N frames - wall time of the first N / 6) /
(N - N / 6), so the start-up (scene, G-buffer, first compilations) is left out.

    .venv/bin/python benchmarks/ibl_speed.py [--baseline REF] [--rounds 3] [--frames 12] \\
        [--pano-width 2048] [--video] [--out ibl_speed.json]

Numba and OpenCV use their default threads (2 on the project's machine), as a user's run
does. Prints markdown tables; --out writes every number as JSON (commits, machine, load).
"""

from __future__ import annotations

import argparse
import dataclasses
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

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_HDR = ROOT.parent / "shared" / "data" / "hdri" / "venice_sunset_1k.hdr"
SUBPACKAGES = ("pipeline", "server", "client", "protocols", "sources")
SCENES = ("diffuse", "glossy 0.2", "mirror", "mixed (demo)")
WARMUP = 2
VIDEO_TURNS = 3  # the --video clip: the frames 3 times over


# --------------------------------------------------------------------------- the worker


def _frames(hdr_path: Path, pano_width: int, count: int) -> list[np.ndarray]:
    """`count` LDR frames (uint8 RGB, pano_width x pano_width / 2): the map turning."""
    from arlight.sources.panorama import read_panorama_image
    from arlight.sources.synthetic_panorama import ldr_frame

    hdr = read_panorama_image(hdr_path)
    ldr = ldr_frame(hdr, 0.18)
    ldr = cv2.resize(ldr, (pano_width, pano_width // 2), interpolation=cv2.INTER_LINEAR)
    return [np.roll(ldr, int(round(i * pano_width / count)), axis=1) for i in range(count)]


def _scene(label: str):
    from arlight.pipeline import ibl_render
    from arlight.pipeline.virtual_scene import Material, VirtualScene

    demo = ibl_render.demo_scene()
    material = {
        "diffuse": Material((0.8, 0.8, 0.8)),
        "glossy 0.2": Material((0.9, 0.9, 0.9), 0.2, 1.0),
        "mirror": Material((0.95, 0.95, 0.95), mirror=True),
    }.get(label)
    if material is None:
        return demo
    return VirtualScene(tuple(dataclasses.replace(o, material=material) for o in demo.objects))


def worker(args: argparse.Namespace) -> dict:
    """Measure this process's arlight; returns the figures and writes the first renders."""
    from arlight.ibl import FrameRenderer, RenderSetup, process_frames
    from arlight.pipeline import ibl_render
    from arlight.pipeline.ibl import IblParams

    ldr = _frames(args.hdr, args.pano_width, args.frames)
    frames = list(process_frames(((i / 30.0, f) for i, f in enumerate(ldr)), IblParams(), False))
    out: dict = {"map_ms": float(np.median([f.process_ms for f in frames[WARMUP:]]))}
    for stage in frames[0].result.timings_ms:
        out[f"map_ms/{stage}"] = float(
            np.median([f.result.timings_ms[stage] for f in frames[WARMUP:]])
        )
    images = {}
    for label in SCENES:
        setup = RenderSetup(
            _scene(label), ibl_render.look_along(np.array([0.0, 0.0, 1.0])), (1280, 720), 75.0
        )
        renderer = FrameRenderer(setup)
        times = []
        for i, frame in enumerate(frames):
            t0 = time.perf_counter()
            rgb = renderer.render(frame)
            times.append((time.perf_counter() - t0) * 1e3)
            if i == 0:
                images[label] = rgb
        out[f"render_ms/{label}"] = float(np.median(times[WARMUP:]))
        for part in ("Pyramid", "Prefilter"):  # the parts of the render its timings name
            parts = [t.get(part, 0.0) for t in renderer.timings_ms[WARMUP:]]
            out[f"render_ms/{label}/{part}"] = float(np.median(parts))
    np.savez_compressed(args.images, **{k.replace(" ", "_"): v for k, v in images.items()})
    if args.video_file:
        out.update(_cli_fps(args.video_file, args.scene_file))
    return out


def _cli_fps(video: Path, scene_file: Path) -> dict:
    """ms per frame of the whole `arlight ibl --render` run (N frames less 2, per frame)."""
    from arlight.cli import main

    total = int(cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FRAME_COUNT))
    first = total // 6  # the start-up and these frames, timed apart
    walls = {}
    for n in (first, total):
        with tempfile.TemporaryDirectory() as tmp:
            argv = ["ibl", str(video), "--render", tmp, "--scene", str(scene_file)]
            argv += ["--out", os.devnull, "--max-frames", str(n)]
            t0 = time.perf_counter()
            code = main(argv)
            walls[n] = time.perf_counter() - t0
            if code != 0:
                raise SystemExit(f"arlight ibl exited {code}")
    return {"cli_ms_per_frame": 1e3 * (walls[total] - walls[first]) / (total - first)}


# --------------------------------------------------------------------------- the driver


def _package_tree(commit: str, where: Path) -> Path:
    """A git worktree of `commit` under `where` and an importable `arlight` package of it
    (its sub-packages linked as setuptools' package-dir maps them); returns the sys.path
    entry."""
    tree = where / "tree"
    subprocess.run(
        ["git", "worktree", "add", "--detach", str(tree), commit],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    pkg = where / "pkg" / "arlight"
    pkg.mkdir(parents=True)
    for entry in (tree / "arlight").iterdir():
        (pkg / entry.name).symlink_to(entry)
    for sub in SUBPACKAGES:
        (pkg / sub).symlink_to(tree / sub)
    return where / "pkg"


def _run_worker(args: argparse.Namespace, path: str | None, images: Path) -> dict:
    env = dict(os.environ)
    if path:
        env["PYTHONPATH"] = path + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--images", str(images)]
    cmd += ["--hdr", str(args.hdr), "--frames", str(args.frames)]
    cmd += ["--pano-width", str(args.pano_width)]
    if args.video:
        cmd += ["--video-file", str(args.video_file), "--scene-file", str(args.scene_file)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    if done.returncode != 0:
        raise SystemExit(f"worker failed ({path or 'current'}):\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


def _write_inputs(args: argparse.Namespace, tmp: Path) -> None:
    """The video and the glossy scene file of --video."""
    frames = _frames(args.hdr, args.pano_width, args.frames)
    args.video_file = tmp / "turning.mp4"
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(args.video_file), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (w, h))
    for f in frames * VIDEO_TURNS:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()
    objects = [
        {
            "name": f"ball_{i}",
            "primitive": {"shape": "sphere", "radius_m": 0.14},
            "world_from_object": [
                [1, 0, 0, (i - 2) * 0.36],
                [0, 1, 0, -0.14],
                [0, 0, 1, 1.6],
                [0, 0, 0, 1],
            ],
            "material": {"albedo": [0.9, 0.9, 0.9], "roughness": 0.2, "metalness": 1.0},
        }
        for i in range(5)
    ]
    args.scene_file = tmp / "glossy.json"
    args.scene_file.write_text(json.dumps({"objects": objects}))


def _commit(ref: str = "HEAD") -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", ref], capture_output=True, text=True, cwd=ROOT, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def driver(args: argparse.Namespace) -> dict:
    report: dict = {"load_before": os.getloadavg()}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        if args.video:
            _write_inputs(args, tmp)
        trees: dict[str, str | None] = {"current": None}
        if args.baseline:
            trees = {"baseline": str(_package_tree(args.baseline, tmp)), "current": None}
        runs: dict[str, list[dict]] = {name: [] for name in trees}
        try:
            for r in range(args.rounds):
                for name, path in trees.items():
                    runs[name].append(_run_worker(args, path, tmp / f"{name}.npz"))
                    print(f"  round {r + 1} {name}: done", flush=True)
            if args.baseline:
                old, new = np.load(tmp / "baseline.npz"), np.load(tmp / "current.npz")
                report["agreement"] = {
                    k: {
                        "psnr_db": _psnr(old[k], new[k]),
                        "max_abs": int(np.abs(old[k].astype(int) - new[k]).max()),
                    }
                    for k in old.files
                }
        finally:
            if args.baseline:
                subprocess.run(
                    ["git", "worktree", "remove", "--force", str(tmp / "tree")],
                    cwd=ROOT,
                    capture_output=True,
                )
    report["load_after"] = os.getloadavg()
    report["figures"] = {
        name: {k: float(np.median([run[k] for run in rs])) for k in rs[0]}
        for name, rs in runs.items()
    }
    report["runs"] = runs
    if args.baseline:
        pairs = list(zip(runs["baseline"], runs["current"], strict=True))
        report["ratio_baseline_over_current"] = {
            k: float(np.median([b[k] / c[k] for b, c in pairs]))
            for k in runs["current"][0]
            if k in runs["baseline"][0] and all(b[k] > 0 and c[k] > 0 for b, c in pairs)
        }
    report.update(
        {
            "benchmark": "ibl_speed",
            "commit": _commit(),
            "baseline": _commit(args.baseline) if args.baseline else None,
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "rounds": args.rounds,
            "frames": args.frames,
            "pano_width": args.pano_width,
        }
    )
    return report


def print_report(report: dict) -> None:
    names = list(report["figures"])
    keys = list(report["figures"][names[-1]])
    keys += [k for k in report["figures"][names[0]] if k not in keys]
    head = " | ".join(names) + (" | baseline / current" if len(names) > 1 else "")
    print(f"\nms per frame (median over {report['rounds']} rounds of each run's median):\n")
    print(f"| figure | {head} |")
    print("|---" * (len(names) + 1 + (len(names) > 1)) + "|")
    for k in keys:
        cells = " | ".join(
            f"{report['figures'][n][k]:.1f}" if k in report["figures"][n] else "-" for n in names
        )
        ratio = report.get("ratio_baseline_over_current", {}).get(k)
        extra = f" | {ratio:.1f}x" if ratio is not None else ""
        print(f"| {k} | {cells}{extra} |")
    for name in names:
        f = report["figures"][name]
        for label in SCENES:
            ms = f["map_ms"] + f[f"render_ms/{label}"]
            print(f"{name}: map + render, {label}: {ms:.0f} ms ({1000 / ms:.1f} FPS)")
    if "agreement" in report:
        print("\nfirst frame, baseline against current (8-bit RGB, 1280x720):")
        for k, a in report["agreement"].items():
            print(f"  {k}: PSNR {a['psnr_db']:.1f} dB, largest difference {a['max_abs']}")
    print(
        f"\nload average before {report['load_before'][0]:.2f}, after {report['load_after'][0]:.2f}"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", metavar="REF", help="a commit to compare against")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--pano-width", type=int, default=2048)
    ap.add_argument("--hdr", type=Path, default=DEFAULT_HDR)
    ap.add_argument("--video", action="store_true", help="also time the whole command")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--images", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--scene-file", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--video-file", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.frames <= WARMUP + 1 or args.rounds < 1 or args.pano_width % 2:
        ap.error("--frames must be > 3, --rounds >= 1, --pano-width even")
    if not args.hdr.is_file():
        print(f"no map at {args.hdr} (--hdr)", file=sys.stderr)
        return 2
    if args.worker:
        print(json.dumps(worker(args)))
        return 0
    report = driver(args)
    print_report(report)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
