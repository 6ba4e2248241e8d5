"""Decoding 360-degree video through the panorama source's decode thread (issue 12, item 9).

Makes one video per size (default 1920x960 and 4096x2048) from a shared HDR map (--hdri,
default ../shared/data/hdri/venice_sunset_1k.hdr, resized; exposure keyed to 0.18, 8-bit
sRGB, the map turning about +y by one full turn over the clip), --seconds long at --fps,
with cv2.VideoWriter (mp4v), then reads it back twice:

- **threaded**: `sources/panorama.py` `open_panorama` (decode on its own thread into a queue
  of 4 frames) while the processing loop runs the per-frame lighting path on each frame
  (`pipeline/ibl.py` `lighting_from_ldr`, default operator and sizes: inverse tone mapping
  of the full frame, SH from 128x64, a 32x16 diffuse map). Per frame: decode ms (read +
  colour conversion, on the decode thread), wait ms (how long the processing loop waited
  for the frame: what decoding still costs the processing path), process ms, and the loop's
  ms per frame;
- **inline**: the same loop decoding each frame itself (cv2.VideoCapture.read + cvtColor,
  then the processing): what the loop would cost without the decode thread.

With --process none the loop only takes the frames (the decoder's own rate).

    OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/ibl_decode.py \\
        [--sizes 1920x960 4096x2048] [--seconds 3] [--fps 30] [--process ibl|none] \\
        [--out ibl_decode.json]

The first frame of each pass is left out of the statistics (warm-up). Median and p90 over
the frames; one shared 2-core machine: compare the two passes, measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from arlight.pipeline.ibl import lighting_from_ldr
from arlight.sources.panorama import open_panorama
from arlight.sources.synthetic_panorama import keyed_exposure, ldr_frame

HERE = Path(__file__).resolve().parent
DEFAULT_HDR = HERE.parents[1] / "shared" / "data" / "hdri" / "venice_sunset_1k.hdr"


def _size(text: str) -> tuple[int, int]:
    w, h = (int(x) for x in text.lower().split("x"))
    if w != 2 * h:
        raise argparse.ArgumentTypeError(f"a panorama is 2:1, got {text}")
    return w, h


def make_video(
    hdr: np.ndarray, size: tuple[int, int], frames: int, fps: float, path: Path
) -> float:
    """Write the turning map as an mp4v video at `size`; returns the seconds it took."""
    w, h = size
    big = cv2.resize(hdr, (w, h), interpolation=cv2.INTER_LINEAR)
    exposure = keyed_exposure(big, 0.18)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        raise SystemExit(f"cv2.VideoWriter cannot write mp4v at {w}x{h}")
    t0 = time.perf_counter()
    ldr = ldr_frame(big, exposure=exposure)  # roll the LDR frame: the map turns about +y
    for i in range(frames):
        shift = int(round(i * w / frames))
        writer.write(cv2.cvtColor(np.roll(ldr, shift, axis=1), cv2.COLOR_RGB2BGR))
    writer.release()
    return time.perf_counter() - t0


def _process(rgb: np.ndarray, mode: str) -> None:
    if mode == "ibl":
        lighting_from_ldr(rgb)


def threaded_pass(path: Path, mode: str) -> dict:
    source = open_panorama(path)
    process_ms, loop_ms = [], []
    t_prev = time.perf_counter()
    for _, rgb in source:
        t0 = time.perf_counter()
        _process(rgb, mode)
        t1 = time.perf_counter()
        process_ms.append((t1 - t0) * 1e3)
        loop_ms.append((t1 - t_prev) * 1e3)
        t_prev = t1
    return {
        "decode_ms": source.decode_ms[1:],
        "wait_ms": source.wait_ms[1 : len(loop_ms)],
        "process_ms": process_ms[1:],
        "loop_ms": loop_ms[1:],
    }


def inline_pass(path: Path, mode: str) -> dict:
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    decode_ms, process_ms, loop_ms = [], [], []
    try:
        while True:
            t0 = time.perf_counter()
            ok, bgr = capture.read()
            if not ok:
                break
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            t1 = time.perf_counter()
            _process(rgb, mode)
            t2 = time.perf_counter()
            decode_ms.append((t1 - t0) * 1e3)
            process_ms.append((t2 - t1) * 1e3)
            loop_ms.append((t2 - t0) * 1e3)
    finally:
        capture.release()
    return {"decode_ms": decode_ms[1:], "process_ms": process_ms[1:], "loop_ms": loop_ms[1:]}


def stats(values: list[float]) -> dict:
    if not values:
        return {"median": math.nan, "p90": math.nan, "n": 0}
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "n": len(a)}


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE
        ).stdout.strip()
    except OSError:
        return ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hdri", type=Path, default=DEFAULT_HDR, help="the HDR map (.hdr)")
    ap.add_argument("--sizes", type=_size, nargs="+", default=[(1920, 960), (4096, 2048)])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--process", choices=("ibl", "none"), default="ibl")
    ap.add_argument("--out", type=Path, help="write every number as JSON")
    args = ap.parse_args(argv)
    bgr = cv2.imread(str(args.hdri), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if bgr is None:
        raise SystemExit(f"{args.hdri}: cannot read this HDR map")
    hdr = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32)
    frames = max(2, int(round(args.seconds * args.fps)))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in args.sizes:
            path = Path(tmp) / f"pano_{w}x{h}.mp4"
            write_s = make_video(hdr, (w, h), frames, args.fps, path)
            threaded = threaded_pass(path, args.process)
            inline = inline_pass(path, args.process)
            row = {
                "size": [w, h],
                "frames": frames,
                "write_s": write_s,
                "bytes": path.stat().st_size,
                "threaded": {k: stats(v) for k, v in threaded.items()},
                "inline": {k: stats(v) for k, v in inline.items()},
                "frames_waited_over_1ms": int(np.sum(np.asarray(threaded["wait_ms"]) > 1.0)),
            }
            rows.append(row)
    print(
        f"{args.hdri.name}: {frames} frames ({args.seconds:g} s at {args.fps:g} fps) per size, "
        f"mp4v; processing: {args.process}; median (p90) ms per frame, first frame left out\n"
    )
    print(
        "| size | decode (thread) | wait in the loop | frames waited > 1 ms | process "
        "| loop, threaded | decode (inline) | loop, inline | saved |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        t, i = r["threaded"], r["inline"]

        def f(s):
            return f"{s['median']:.1f} ({s['p90']:.1f})"

        saved = 1.0 - t["loop_ms"]["median"] / i["loop_ms"]["median"]
        print(
            f"| {r['size'][0]}x{r['size'][1]} | {f(t['decode_ms'])} | {f(t['wait_ms'])} | "
            f"{r['frames_waited_over_1ms']}/{t['wait_ms']['n']} | {f(t['process_ms'])} | "
            f"{f(t['loop_ms'])} | {f(i['decode_ms'])} | {f(i['loop_ms'])} | "
            f"{saved * 100:.0f} % |"
        )
    if args.out:
        args.out.write_text(
            json.dumps(
                {
                    "commit": _commit(),
                    "machine": platform.platform(),
                    "python": sys.version.split()[0],
                    "opencv": cv2.__version__,
                    "hdri": str(args.hdri),
                    "process": args.process,
                    "rows": rows,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
