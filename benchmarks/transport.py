"""Transport benchmark: the streaming service with the pipeline replaced by an identity step.

    .venv/bin/python benchmarks/transport.py [--frames 60] [--warmup 5] [--json FILE]

A real `arlight.server.Server` runs in a separate process (so client and server do not share
one interpreter lock) on a loopback TCP port, with an identity compute step (this benchmark
only). The client sends 640 x 480 RGB-D frames of the built-in synthetic scene, once per
codec combination, and reports:

- fps: lossless mode, the server's credit window full, frames encoded as they are sent;
- latency median / p99 (ms): one frame in flight at a time, from before the frame is encoded
  to its Result decoded on the client: what the transport adds to a frame (encode, send,
  server decode and input conversion, Result encode and send, client decode);
- KiB per frame: all parts of the Frame message;
- encode / decode ms: median of encode(Frame) and decode(parts) alone, in this process.

Nothing is asserted: figures, not tests (docs/architecture.md).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import time

import numpy as np
import zmq

from arlight.protocols import (
    COLOR_CODECS,
    DEPTH_CODECS,
    PROTOCOL_VERSION,
    Frame,
    Hello,
    Result,
    SessionConfig,
    Welcome,
    decode,
    encode,
)

WIDTH, HEIGHT = 640, 480


def identity_step(frame, session, render_light, deadline):
    """Stands in for Pipeline.process: a constant result, no compute."""
    from arlight.core.frames import Confidence, FrameResult

    sh = np.zeros(16)
    return FrameResult(
        timestamp=frame.timestamp,
        sh=sh,
        sh_camera=sh,
        dominant_direction_world=np.zeros(3),
        dominant_direction_camera=np.zeros(3),
        intensity=0.0,
        confidence=Confidence(),
        pose=np.eye(4),
        timings_ms={},
    )


def serve(port: int) -> None:
    """The server process: runs until stdin closes."""
    from arlight.server.server import Server, ServerOptions

    server = Server(
        ServerOptions(bind=f"tcp://127.0.0.1:{port}", workers=1, log_interval_s=3600.0),
        process=identity_step,
    ).start()
    print("ready", flush=True)
    sys.stdin.read()
    server.stop()


def make_frames(n: int = 8):
    from arlight.sources.source import sequence_source
    from arlight.sources.synthetic import make_sequence

    seq = make_sequence(num_frames=n, width=WIDTH, height=HEIGHT)
    source = sequence_source("synthetic", seq.camera, seq.frames)
    return source, list(source.frames())


class Client:
    def __init__(self, address: str, source, color: str, depth: str, session: str):
        self.socket = zmq.Context.instance().socket(zmq.DEALER)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.connect(address)
        self.color, self.depth = color, depth
        config = SessionConfig(
            session=session,
            calibration=source.calibration,
            depth_scale=source.depth_scale,
            mode="lossless",
        )
        self.socket.send_multipart(encode(Hello(PROTOCOL_VERSION, config)), copy=False)
        welcome = self.receive(30.0)
        if not isinstance(welcome, Welcome):
            raise RuntimeError(f"no Welcome: {welcome}")
        self.credits = welcome.credits
        self.seq = 0

    def receive(self, timeout_s: float = 30.0):
        while True:
            if not self.socket.poll(int(timeout_s * 1000)):
                raise TimeoutError("the server did not answer")
            message = decode(self.socket.recv_multipart(copy=False))
            if type(message).__name__ != "Heartbeat":
                return message

    def frame(self, f) -> list:
        parts = encode(
            Frame(self.seq, time.time(), f.color, f.depth, None, None, self.color, self.depth)
        )
        self.seq += 1
        return parts

    def result(self):
        message = self.receive()
        if not isinstance(message, Result):
            raise RuntimeError(f"expected a Result, got {message}")
        return message

    def close(self) -> None:
        self.socket.close(linger=0)


def bench_combo(address: str, source, frames, color: str, depth: str, n: int, warmup: int) -> dict:
    # codec cost alone, in this process
    encode_ms, decode_ms, sizes = [], [], []
    for i in range(max(n // 2, 10)):
        f = frames[i % len(frames)]
        t0 = time.perf_counter()
        parts = encode(Frame(i, 0.0, f.color, f.depth, None, None, color, depth))
        t1 = time.perf_counter()
        decode(parts)
        t2 = time.perf_counter()
        encode_ms.append((t1 - t0) * 1e3)
        decode_ms.append((t2 - t1) * 1e3)
        sizes.append(sum(len(memoryview(p)) for p in parts))

    # latency: one frame in flight, capture (before encode) -> Result decoded
    client = Client(address, source, color, depth, f"lat-{color}-{depth}")
    latency_ms = []
    for i in range(warmup + n):
        t0 = time.perf_counter()
        client.socket.send_multipart(client.frame(frames[i % len(frames)]), copy=False)
        client.result()
        if i >= warmup:
            latency_ms.append((time.perf_counter() - t0) * 1e3)
    client.close()

    # throughput: credit window full, encoding as we go
    client = Client(address, source, color, depth, f"fps-{color}-{depth}")
    in_flight = 0
    for i in range(warmup):
        client.socket.send_multipart(client.frame(frames[i % len(frames)]), copy=False)
        client.result()
    t0 = time.perf_counter()
    sent = received = 0
    while received < n:
        while sent < n and in_flight < client.credits:
            client.socket.send_multipart(client.frame(frames[sent % len(frames)]), copy=False)
            sent += 1
            in_flight += 1
        client.result()
        received += 1
        in_flight -= 1
    fps = n / (time.perf_counter() - t0)
    client.close()
    lat = np.asarray(latency_ms)
    return {
        "color": color,
        "depth": depth,
        "fps": fps,
        "latency_median_ms": float(np.median(lat)),
        "latency_p99_ms": float(np.percentile(lat, 99)),
        "kib_per_frame": float(np.mean(sizes)) / 1024,
        "encode_ms": float(np.median(encode_ms)),
        "decode_ms": float(np.median(decode_ms)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="timed frames per combination")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--color", nargs="+", default=list(COLOR_CODECS), choices=COLOR_CODECS)
    parser.add_argument("--depth", nargs="+", default=list(DEPTH_CODECS), choices=DEPTH_CODECS)
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    parser.add_argument("--serve", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(args.serve)
        return 0

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve", str(port)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        if server.stdout.readline().strip() != "ready":
            raise RuntimeError("the server process did not start")
        address = f"tcp://127.0.0.1:{port}"
        source, frames = make_frames()
        print(
            f"transport benchmark: {WIDTH}x{HEIGHT} RGB-D (synthetic scene), identity step "
            f"in a server process on {address}; {args.frames} frames per row "
            f"(+{args.warmup} warm-up); {os.cpu_count()} CPU cores",
            file=sys.stderr,
        )
        header = (
            f"{'colour':<7}{'depth':<7}{'fps':>8}{'lat med ms':>12}{'lat p99 ms':>12}"
            f"{'KiB/frame':>11}{'enc ms':>9}{'dec ms':>9}"
        )
        print(header)
        print("-" * len(header))
        rows = []
        for color in args.color:
            for depth in args.depth:
                row = bench_combo(address, source, frames, color, depth, args.frames, args.warmup)
                rows.append(row)
                print(
                    f"{color:<7}{depth:<7}{row['fps']:>8.1f}{row['latency_median_ms']:>12.2f}"
                    f"{row['latency_p99_ms']:>12.2f}{row['kib_per_frame']:>11.1f}"
                    f"{row['encode_ms']:>9.2f}{row['decode_ms']:>9.2f}",
                    flush=True,
                )
    finally:
        server.stdin.close()
        server.wait(30)
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            cwd=os.path.dirname(os.path.abspath(__file__)),
        ).stdout.strip()
        record = {
            "benchmark": "transport",
            "commit": commit,
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "zmq": zmq.zmq_version(),
            "width": WIDTH,
            "height": HEIGHT,
            "frames": args.frames,
            "rows": rows,
        }
        with open(args.json, "w") as f:
            json.dump(record, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
