"""`arlight serve --ray`: N lossless sessions against a local Ray of 1 and 2 actors' CPUs.

    nice -n 5 .venv/bin/python benchmarks/ray_sessions.py [--sessions 1 2 4] [--cpus 1 2]
        [--frames 30] [--size 160x120] [--preset fast] [--json FILE]

For each Ray size (`ray.init(num_cpus=C)`: the fast preset's actors ask 1 CPU each, so C
actors run at once; a session beyond that waits for a free one) and each number of
sessions N, an in-process server (server/server.py with arlight/ray_serve.py's RayCompute,
the step `arlight serve --ray` uses) serves N capture clients (client/capture.py, lossless,
rate max, credits 4) streaming the built-in synthetic scene with its poses. Reported: Results
delivered per second over the run (first frame sent to last Result, every actor's start
included), the send-to-Result latency (median, p95) and the first Result's latency (the
actor's start: process, imports, volume). Every frame must get exactly one Result.

Two costs per frame on their own, for the cluster argument: the server's I/O path (ZeroMQ
receive, decode, encode, send; an identity compute step, no Ray) as Results/s of one
session, and the Ray round trip of one frame (a FrameInput to an actor that returns a
result of the same size through the object store) as ms per call.

The server, the clients and the Ray driver share this process; the actors are Ray worker
processes. Figures, not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import threading
import time

import numpy as np

from arlight.client.capture import CaptureClient, StreamOptions
from arlight.server.server import Server, ServerOptions
from arlight.sources.source import open_source


def stream_all(server: Server, sources: list, preset: str) -> dict:
    results: list[list[int]] = [[] for _ in sources]
    summaries: list = [None] * len(sources)

    def run(i: int) -> None:
        options = StreamOptions(
            server=server.connect_address,
            session=f"s{i}",
            mode="lossless",
            rate="max",
            preset=preset,
        )
        client = CaptureClient(
            sources[i], options, on_result=lambda r, _w, i=i: results[i].append(r.seq)
        )
        summaries[i] = client.run()

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(sources))]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    n_frames = sources[0].num_frames
    for seqs in results:
        assert sorted(seqs) == list(range(n_frames)), "a frame lost or answered twice"
    lat = np.concatenate([np.asarray(s.latencies_s) for s in summaries]) * 1e3
    first = [s.latencies_s[0] * 1e3 for s in summaries]
    total = sum(len(r) for r in results)
    return {
        "results": total,
        "wall_s": wall,
        "results_per_s": total / wall,
        "latency_ms_median": float(np.median(lat)),
        "latency_ms_p95": float(np.percentile(lat, 95)),
        "first_result_ms_median": float(np.median(first)),
    }


def io_path(size: tuple[int, int], frames: int) -> dict:
    """One session through the server with an identity step: the I/O path's cost."""
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).with_name("transport.py")  # its identity step
    spec = importlib.util.spec_from_file_location("arlight_transport_bench", path)
    transport = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(transport)
    source = open_source("synthetic", use_poses=True, max_frames=frames, synthetic_size=size)
    with Server(ServerOptions(bind="tcp://127.0.0.1:*"), process=transport.identity_step) as server:
        return stream_all(server, [source], "fast")


class Echo:
    """An actor returning an array as large as the frame it gets (the object store both ways)."""

    def process(self, frame):
        return np.empty_like(frame.color), np.empty_like(frame.depth)


def ray_round_trip(ray, size: tuple[int, int], calls: int = 200) -> dict:
    source = open_source("synthetic", use_poses=True, max_frames=1, synthetic_size=size)
    from arlight.core.frames import FrameInput

    f = next(iter(source.frames()))
    frame = FrameInput(
        color=f.color,
        depth=f.depth,
        depth_scale=source.depth_scale,
        timestamp=f.timestamp,
        pose=f.pose,
    )
    actor = ray.remote(Echo).options(num_cpus=0).remote()
    ray.get(actor.process.remote(frame))
    t0 = time.perf_counter()
    for _ in range(calls):
        ray.get(actor.process.remote(frame))
    ms = (time.perf_counter() - t0) / calls * 1e3
    ray.kill(actor)
    return {"ms_per_call": ms, "frame_bytes": int(f.color.nbytes + f.depth.nbytes)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--cpus", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--json")
    args = ap.parse_args()
    size = tuple(int(x) for x in args.size.split("x"))
    import ray

    from arlight.ray_serve import RayCompute

    report = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "size": args.size,
        "preset": args.preset,
        "frames": args.frames,
        "runs": [],
    }
    report["io_path"] = io_path(size, max(args.frames, 60))
    print(
        f"I/O path, identity step, 1 session: {report['io_path']['results_per_s']:.0f} "
        f"Results/s, latency median {report['io_path']['latency_ms_median']:.1f} ms",
        flush=True,
    )
    for cpus in args.cpus:
        ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
        try:
            if cpus == args.cpus[0]:
                report["ray_round_trip"] = ray_round_trip(ray, size)
                print(f"Ray round trip of one frame: {report['ray_round_trip']}", flush=True)
            for n in args.sessions:
                sources = [
                    open_source(
                        "synthetic", use_poses=True, max_frames=args.frames, synthetic_size=size
                    )
                    for _ in range(n)
                ]
                compute = RayCompute(ray)
                # a session waiting for a free actor must not hit the frame deadline
                options = ServerOptions(
                    bind="tcp://127.0.0.1:*", log_interval_s=600, frame_deadline_s=600
                )
                with Server(options, process=compute) as server:
                    run = stream_all(server, sources, args.preset)
                compute.close()
                run.update(cpus=cpus, sessions=n)
                report["runs"].append(run)
                print(
                    f"Ray {cpus} CPU(s), {n} session(s): {run['results_per_s']:.1f} "
                    f"Results/s, latency median {run['latency_ms_median']:.0f} ms, p95 "
                    f"{run['latency_ms_p95']:.0f} ms, first Result "
                    f"{run['first_result_ms_median']:.0f} ms ({run['wall_s']:.1f} s)",
                    flush=True,
                )
        finally:
            ray.shutdown()
    print(
        "\n| Ray CPUs (actors at once) | sessions | Results/s | latency median / p95 ms "
        "| first Result ms |\n|---|---|---|---|---|"
    )
    for r in report["runs"]:
        print(
            f"| {r['cpus']} | {r['sessions']} | {r['results_per_s']:.1f} | "
            f"{r['latency_ms_median']:.0f} / {r['latency_ms_p95']:.0f} | "
            f"{r['first_result_ms_median']:.0f} |"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
