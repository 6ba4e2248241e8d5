"""How the cost grows: milliseconds per stage against image size, voxel count and the number
of concurrent sessions, on the built-in synthetic scene.

* image size: `arlight bench --sweep size=...` (the built-in scene rendered at each size, its
  camera scaled), one preset;
* voxels: `--sweep volume_resolution=...` at 640x480 (the volume's edge in voxels; its
  metric size stays, so the voxels shrink);
* sessions: a real server (`arlight.server.Server`, loopback TCP) with `--workers` worker
  threads and N capture clients streaming the built-in scene at once (lossless, as fast as
  the server takes them); per session the frames per second it got, and all together.

Prints three markdown tables, names the stage that grows fastest with the image (its
milliseconds per megapixel at the largest size against the smallest), and writes
scaling.png (per-stage milliseconds against pixels and against voxels) and scaling.json to
--out.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/scaling.py [--preset fast]
        [--sizes 160x120 320x240 640x480 1280x960] [--volumes 64 128 256 512]
        [--sessions 1 2 4] [--frames 6] [--out scaling-report]
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

from arlight.bench import BUILT_IN, run_benchmark
from arlight.pipeline.runtime import configure_process

STAGES = ("Input", "Reconstruct", "Surface", "DynGeo", "RadTransfer", "LightEst")


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def stage_table(report: dict, label: str) -> tuple[str, dict]:
    """Markdown rows (one per sweep value) of per-stage median ms, and those figures."""
    rows = [
        f"| {label} | " + " | ".join(STAGES) + " | total | FPS |",
        "|---|" + "---|" * (len(STAGES) + 2),
    ]
    figures = {}
    for c in report["configs"].values():
        if c["sweep"] is None:
            continue
        ms = {s: c["stages_ms"][s]["median"] for s in STAGES}
        value = c["value"]
        value = "x".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)
        figures[value] = {**ms, "total": c["total_ms"]["median"], "fps": c["fps"]}
        rows.append(
            f"| {value} | "
            + " | ".join(f"{ms[s]:.1f}" for s in STAGES)
            + f" | {c['total_ms']['median']:.1f} | {c['fps']:.2f} |"
        )
    return "\n".join(rows), figures


def sweep(key: str, values: list, preset: str, frames: int) -> dict:
    """One bench run: the preset with `key` set to each value in turn."""
    return run_benchmark([BUILT_IN], [preset], [(key, values)], frames, 2, {}, progress=False)


def concurrent_sessions(n: int, preset: str, frames: int, workers: int) -> dict:
    """n capture clients at once against one server; per-session and total frames/s."""
    from arlight.client.capture import CaptureClient, StreamOptions
    from arlight.server.server import Server, ServerOptions
    from arlight.sources.source import sequence_source
    from arlight.sources.synthetic import make_sequence

    scene = make_sequence(num_frames=frames + 2)
    server = Server(ServerOptions(bind="tcp://127.0.0.1:*", workers=workers)).start()
    summaries: list = [None] * n
    try:

        def run(i: int) -> None:
            source = sequence_source("synthetic", scene.camera, scene.frames)
            client = CaptureClient(
                source,
                StreamOptions(
                    server=server.connect_address,
                    session=f"scaling-{i}",
                    mode="lossless",
                    rate="max",
                    preset=preset,
                    client_name=f"scaling-{i}",
                ),
            )
            summaries[i] = client.run()

        threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
    finally:
        server.stop()
    per = [s.results / s.elapsed_s if s.elapsed_s > 0 else 0.0 for s in summaries]
    return {
        "sessions": n,
        "workers": workers,
        "per_session_fps": per,
        "total_fps": sum(s.results for s in summaries) / wall,
        "errors": sum(len(s.errors) for s in summaries),
    }


def plot(sizes: dict, volumes: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    px = [np.prod(_size(k)) / 1e6 for k in sizes]
    for s in STAGES + ("total",):
        axes[0].plot(px, [v[s] for v in sizes.values()], "o-", label=s)
    axes[0].set(
        xlabel="megapixels",
        ylabel="ms per frame (median)",
        xscale="log",
        yscale="log",
        title="cost against image size",
    )
    vox = [int(k) ** 3 / 1e6 for k in volumes]
    for s in STAGES + ("total",):
        axes[1].plot(vox, [v[s] for v in volumes.values()], "o-", label=s)
    axes[1].set(
        xlabel="voxels (millions, edge^3)",
        ylabel="ms per frame (median)",
        xscale="log",
        yscale="log",
        title="cost against volume resolution (640x480)",
    )
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--sizes", nargs="+", default=["160x120", "320x240", "640x480", "1280x960"])
    parser.add_argument("--volumes", nargs="+", type=int, default=[64, 128, 256, 512])
    parser.add_argument("--sessions", nargs="+", type=int, default=[1, 2, 4])
    parser.add_argument("--workers", type=int, default=2, help="server worker threads")
    parser.add_argument("--frames", type=int, default=6, help="timed frames per point")
    parser.add_argument("--out", type=Path, default=Path("scaling-report"))
    args = parser.parse_args(argv)
    configure_process()
    args.out.mkdir(parents=True, exist_ok=True)
    size_table, sizes = stage_table(
        sweep("size", [_size(s) for s in args.sizes], args.preset, args.frames), "size"
    )
    sizes = dict(zip(args.sizes, sizes.values(), strict=True))
    print(f"## {args.preset}: per-stage ms against image size\n\n{size_table}\n", flush=True)
    volume_table, volumes = stage_table(
        sweep("volume_resolution", args.volumes, args.preset, args.frames), "volume_resolution"
    )
    print(
        f"## {args.preset}: per-stage ms against volume resolution (640x480)\n\n{volume_table}\n",
        flush=True,
    )
    first, last = args.sizes[0], args.sizes[-1]
    mp = {k: np.prod(_size(k)) / 1e6 for k in (first, last)}
    growth = {
        s: (sizes[last][s] / mp[last]) / max(sizes[first][s] / mp[first], 1e-9) for s in STAGES
    }
    fastest = max(growth, key=growth.get)
    print(
        f"ms per megapixel at {last} against {first}: "
        + ", ".join(f"{s} {g:.2f}x" for s, g in growth.items())
        + f"; fastest growing: {fastest}\n"
    )
    sessions = [
        concurrent_sessions(n, args.preset, args.frames, args.workers) for n in args.sessions
    ]
    lines = ["| sessions | per-session FPS (each) | total FPS | errors |", "|---|---|---|---|"]
    for s in sessions:
        lines.append(
            f"| {s['sessions']} | "
            + " ".join(f"{f:.2f}" for f in s["per_session_fps"])
            + f" | {s['total_fps']:.2f} | {s['errors']} |"
        )
    print(
        f"## {args.preset}: concurrent sessions ({args.workers} server workers, 640x480, "
        "lossless)\n\n" + "\n".join(lines)
    )
    plot(sizes, volumes, args.out / "scaling.png")
    (args.out / "scaling.json").write_text(
        json.dumps(
            {
                "preset": args.preset,
                "sizes": sizes,
                "volumes": volumes,
                "growth_per_mp": growth,
                "sessions": sessions,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {args.out / 'scaling.png'} and {args.out / 'scaling.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
