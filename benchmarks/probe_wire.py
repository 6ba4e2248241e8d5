"""The reflection probe on the wire (issue 33, item 3): bytes a Result carries and the codec's
milliseconds each way, at several probe sizes, level 0 alone and with every mip level.

On one sequence with a mirror object (default: the corpus room c021), the `fast` Pipeline
makes the probe of its frame --frames - 1 at each size; then the Result's codec (RGB9E5
texels, one zstd frame: protocols/probe.py) and, for the choice recorded in SPEC.md,
float16 RGB texels with the same zstd, are each timed --repeat times after a warm-up
(encode: packing the texels and compressing; decode: inflating and unpacking to float32).
Prints a Markdown table (bytes; median ms with p10-p90) and writes a JSON record (commit,
machine, load average). Never time a single call: the same probe is coded again and again.

    nice -n 10 .venv/bin/python benchmarks/probe_wire.py [SEQ] [--sizes 64 128]
        [--frames 3] [--repeat 30] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zstandard

from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.probe import ProbeSettings
from arlight.pipeline.runtime import configure_process
from arlight.protocols.probe import (
    PROBE_ZSTD_LEVEL,
    ProbeCube,
    rgb9e5_decode,
)
from arlight.report import commit as git_commit
from arlight.sources.sequence import open_sequence
from arlight.sources.virtual_scene_file import load_virtual_scene

DEFAULT_SEQ = Path.home() / ".cache" / "arlight" / "corpus" / "c021_room_st_peters_square_night"


def _timed(fn: Callable[[], object], repeat: int) -> list[float]:
    fn()  # warm-up
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def make_probe(folder: Path, size: int, frames: int) -> list[np.ndarray]:
    """The probe's levels (world axes, float32) of the sequence's frame `frames - 1`."""
    seq = open_sequence(folder, use_poses=True, max_frames=frames)
    scene = load_virtual_scene(folder / "ar" / "virtual_scene.json")
    pipe = Pipeline(Config.from_preset("fast", probe_size=size), seq.camera, scene)
    for frame in seq.frames:
        pipe.process(frame)
    if pipe.last_probe is None:
        raise SystemExit(f"{folder}: no probe was made (no mirror or glossy object placed)")
    return [np.asarray(lv, np.float32) for lv in pipe.last_probe.mips.levels]


def codecs(levels: list[np.ndarray]) -> dict[str, tuple[Callable, Callable]]:
    """name -> (encode() -> bytes, decode(bytes) -> levels) of the levels given."""
    sizes = [lv.shape for lv in levels]
    zc = zstandard.ZstdCompressor(level=PROBE_ZSTD_LEVEL)
    zd = zstandard.ZstdDecompressor()

    def unflatten(flat: np.ndarray) -> list[np.ndarray]:
        out, start = [], 0
        for shape in sizes:
            count = int(np.prod(shape[:3]))
            out.append(flat[start : start + count].reshape(shape))
            start += count
        return out

    def rgb9e5_enc() -> bytes:
        cube = ProbeCube([0.0, 0.0, 0.0], levels, list(np.linspace(0, 1, len(levels))))
        parts: list = []
        cube._pack(parts, "probe")
        return bytes(parts[0])

    def rgb9e5_dec(data: bytes) -> list[np.ndarray]:
        return unflatten(rgb9e5_decode(np.frombuffer(zd.decompress(data), "<u4")))

    def f16_enc() -> bytes:
        flat = np.concatenate([lv.reshape(-1, 3) for lv in levels]).astype("<f2")
        return zc.compress(flat.tobytes())

    def f16_dec(data: bytes) -> list[np.ndarray]:
        flat = np.frombuffer(zd.decompress(data), "<f2").reshape(-1, 3).astype(np.float32)
        return unflatten(flat.reshape(-1, 3))

    return {"rgb9e5+zstd": (rgb9e5_enc, rgb9e5_dec), "float16+zstd": (f16_enc, f16_dec)}


def measure(levels: list[np.ndarray], repeat: int) -> dict:
    """{codec: {bytes, raw_bytes, encode_ms, decode_ms, max_rel_error}}."""
    out = {}
    for name, (enc, dec) in codecs(levels).items():
        data = enc()
        back = dec(data)
        rel = max(
            float((np.abs(a - b).max(-1) / np.maximum(a.max(-1), 1e-6)).max())
            for a, b in zip(levels, back, strict=True)
        )
        texels = sum(int(np.prod(lv.shape[:3])) for lv in levels)
        out[name] = {
            "bytes": len(data),
            "raw_bytes": texels * (4 if name.startswith("rgb9e5") else 6),
            "encode_ms": _timed(enc, repeat),
            "decode_ms": _timed(lambda d=data, f=dec: f(d), repeat),
            "max_rel_error": rel,
        }
    return out


def _ms(values: list[float]) -> str:
    return (
        f"{np.median(values):.2f} ({np.percentile(values, 10):.2f}-{np.percentile(values, 90):.2f})"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", nargs="?", type=Path, default=DEFAULT_SEQ)
    parser.add_argument("--sizes", nargs="+", type=int, default=[64, 128])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=30)
    parser.add_argument("--json", type=Path, default=Path("probe_wire.json"))
    args = parser.parse_args(argv)
    if not (args.sequence / "ar" / "virtual_scene.json").is_file():
        parser.error(f"{args.sequence} has no ar/virtual_scene.json (render one: arlight synth)")
    for s in args.sizes:
        try:
            ProbeSettings(size=s)
        except ValueError as exc:
            parser.error(f"--sizes: {exc}")
    if args.frames < 1 or args.repeat < 1:
        parser.error("--frames and --repeat must be at least 1")
    configure_process()
    load_before = os.getloadavg()
    figures: dict = {}
    for size in args.sizes:
        levels = make_probe(args.sequence, size, args.frames)
        figures[size] = {
            "level 0": measure(levels[:1], args.repeat),
            "every level": measure(levels, args.repeat),
        }
    load_after = os.getloadavg()
    print("| texels a face | levels | codec | bytes (before zstd) | encode ms | decode ms |")
    print("|---|---|---|---|---|---|")
    for size, by_levels in figures.items():
        for which, by_codec in by_levels.items():
            for name, f in by_codec.items():
                print(
                    f"| {size} | {which} | {name} | {f['bytes']:,} ({f['raw_bytes']:,}) | "
                    f"{_ms(f['encode_ms'])} | {_ms(f['decode_ms'])} |"
                )
    worst = {
        name: max(f[name]["max_rel_error"] for s in figures.values() for f in s.values())
        for name in ("rgb9e5+zstd", "float16+zstd")
    }
    print(
        f"ms: median (p10-p90) over {args.repeat} repeats; load average "
        f"{load_before[0]:.1f} -> {load_after[0]:.1f}; largest error relative to the "
        "texel's brightest channel (above 1e-6): "
        + ", ".join(f"{name} {err:.4f}" for name, err in worst.items())
    )
    commit = git_commit()
    record = {
        "sequence": str(args.sequence),
        "frames": args.frames,
        "commit": commit,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "load_average_1min": [load_before[0], load_after[0]],
        "figures": {str(k): v for k, v in figures.items()},
    }
    args.json.write_text(json.dumps(record, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
