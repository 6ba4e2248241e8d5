"""Lossless depth codecs of the wire protocol on real depth: ratio, encode and decode time.

Reads the real 640 x 480 uint16 depth images under ../shared/data/real (7-Scenes, ICL-NUIM,
the TUM-layout corner sequence, the TUM and SUN single frames), encodes and decodes each
with every depth codec through arlight.protocols (the same calls encode()/decode() make,
validation included) and prints, per codec: compression ratio (raw bytes / payload bytes,
over all frames together, and its range over the frames), encode and decode milliseconds
(median and 90th percentile over frames of the best of --repeats calls). Every decode is
checked to be bit-exact.

    .venv/bin/python benchmarks/depth_codecs.py [--repeats 3] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from arlight.protocols import decode_depth, encode_depth

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

# name -> (codec, encode keyword arguments)
CODECS = {
    "raw": ("raw", {}),
    "zstd-1": ("zstd", {"zstd_level": 1}),
    "zstd-3": ("zstd", {"zstd_level": 3}),
    "rvl": ("rvl", {}),
    "png-1": ("png", {"png_compression": 1}),
    "png-3": ("png", {"png_compression": 3}),
}


def load_depth(root: Path) -> dict[str, list[np.ndarray]]:
    """Real depth images as on the wire (uint16, the sensor's own units), by data set."""
    sets: dict[str, list[np.ndarray]] = {}

    def read(path: Path) -> np.ndarray:
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if d is None or d.dtype != np.uint16 or d.ndim != 2:
            raise SystemExit(f"{path}: not a uint16 depth image")
        return d

    sets["7scenes"] = [read(p) for p in sorted((root / "7scenes_redkitchen").glob("*.depth.png"))]
    sets["icl_nuim"] = [read(p) for p in sorted((root / "icl_nuim_livingroom/depth").glob("*.png"))]
    sets["corner"] = [read(p) for p in sorted((root / "corner_18frames/depth").glob("*.png"))]
    singles = []
    if (root / "single_frames/TUM_depth.png").exists():
        singles.append(read(root / "single_frames/TUM_depth.png"))
    if (root / "single_frames/SUN_depth.png").exists():
        v = read(root / "single_frames/SUN_depth.png").astype(np.uint32)
        singles.append((((v >> 3) | (v << 13)) & 0xFFFF).astype(np.uint16))  # to millimetres
    sets["tum+sun"] = singles
    return {k: v for k, v in sets.items() if v}


def best_ms(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3, out


def measure(frames: list[np.ndarray], repeats: int) -> dict[str, dict]:
    table = {}
    for name, (codec, kwargs) in CODECS.items():
        encode_depth(frames[0], codec, **kwargs)  # warm-up (RVL JIT, caches)
        raw_bytes = payload_bytes = 0
        ratios, enc_ms, dec_ms = [], [], []
        for depth in frames:
            t_enc, (payload, meta) = best_ms(
                lambda d=depth, c=codec, kw=kwargs: encode_depth(d, c, **kw), repeats
            )
            t_dec, back = best_ms(lambda p=payload, m=meta: decode_depth(p, m), repeats)
            if not np.array_equal(back, depth):
                raise SystemExit(f"{name}: decode is not bit-exact")
            n = len(memoryview(payload).cast("B"))
            raw_bytes += depth.nbytes
            payload_bytes += n
            ratios.append(depth.nbytes / n)
            enc_ms.append(t_enc)
            dec_ms.append(t_dec)
        table[name] = {
            "ratio": raw_bytes / payload_bytes,
            "ratio_min": min(ratios),
            "ratio_max": max(ratios),
            "encode_ms_median": float(np.median(enc_ms)),
            "encode_ms_p90": float(np.percentile(enc_ms, 90)),
            "decode_ms_median": float(np.median(dec_ms)),
            "decode_ms_p90": float(np.percentile(dec_ms, 90)),
            "frames": len(frames),
        }
    return table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--repeats", type=int, default=3, help="calls per frame; best counts")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        print(f"no real depth data at {args.data} (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    sets = load_depth(args.data)
    every = [d for frames in sets.values() for d in frames]
    sizes = sorted({f"{d.shape[1]}x{d.shape[0]}" for d in every})
    print(
        f"{len(every)} real depth frames ({', '.join(f'{k} {len(v)}' for k, v in sets.items())}),"
        f" sizes {', '.join(sizes)}; best of {args.repeats} calls per frame\n"
    )
    results = {"all": measure(every, args.repeats)}
    for key, frames in sets.items():
        results[key] = measure(frames, args.repeats)
    head = (
        f"{'codec':8} {'ratio':>6} {'(range)':>13} {'enc ms':>7} {'p90':>6} "
        f"{'dec ms':>7} {'p90':>6}"
    )
    for key, table in results.items():
        print(f"[{key}]")
        print(head)
        for name, r in table.items():
            print(
                f"{name:8} {r['ratio']:6.2f} {r['ratio_min']:6.2f}-{r['ratio_max']:<6.2f} "
                f"{r['encode_ms_median']:7.2f} {r['encode_ms_p90']:6.2f} "
                f"{r['decode_ms_median']:7.2f} {r['decode_ms_p90']:6.2f}"
            )
        print()
    if args.json:
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False
            ).stdout.strip()
        except OSError:
            commit = ""
        record = {
            "commit": commit,
            "machine": platform.platform(),
            "processor": platform.processor(),
            "python": platform.python_version(),
            "cv2": cv2.__version__,
            "repeats": args.repeats,
            "results": results,
        }
        args.json.write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
