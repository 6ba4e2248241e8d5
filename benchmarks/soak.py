"""Soak benchmark: lossless sessions under load and faults, against a real `arlight serve`.

    .venv/bin/python benchmarks/soak.py [--sessions 8] [--duration 600] [--size 80x60]
        [--preset fast] [--workers 2] [--kill-at 0.5] [--flood-rate 200]
        [--stuck-displays 2] [--json FILE]

Runs `arlight serve` as a child process (the real pipeline, at a small image size) and, for
`--duration` seconds:

- `--sessions` capture clients (client/capture.py, lossless, as fast as the credits allow)
  stream the built-in synthetic scene (looped, with its poses), each session's timestamps
  offset so a Result names its session and frame;
- at `--kill-at` x duration the server is killed (SIGKILL: no Bye, nothing flushed) and
  started again on the same port; the clients reconnect and send their unacknowledged
  frames again;
- a hostile peer floods the server (`--flood-rate` messages per second: garbage, truncated
  and bit-flipped frames, frames from no session, seq out of range, headers of many
  containers (issue 39), and Hellos over the budgets, which must be refused);
- `--stuck-displays` display peers subscribe to the sessions, keep themselves alive with
  heartbeats and never read (their queues fill; the sessions must not notice);
- one reading display per session (client/display.py, `--follow`) counts every Result the
  server broadcasts: a seq it sees twice was processed twice, which happens only for a
  frame in flight when the server was killed (its Result lost; the next server processes
  it again). Reported, not a failure: delivery to the capture application stays
  exactly-once.

Then it stops the server with SIGTERM and reports, per session and in all: frames sent (taken
from the source), Results received, lost (sent, never answered by a Result), final Errors,
duplicated and out-of-order Results (as the capture application sees them), Results naming
the wrong frame, reconnects, the largest gap between a session's Results (outside the kill
and the reconnect after it); and the server's RSS at start, after warm-up (the first
`--warmup` fraction of each server life), its peak after warm-up and at the end, with the
post-warm-up slope. It exits 1 if any frame is lost, failed, duplicated, out of order or
mixed, or if a budget-busting Hello was welcomed. Figures, not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

import msgpack
import numpy as np
import zmq

from arlight.client.capture import CaptureClient, StreamOptions
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.protocols import (
    PROTOCOL_VERSION,
    Error,
    Frame,
    Heartbeat,
    Hello,
    SessionConfig,
    Welcome,
    decode,
    encode,
)
from arlight.sources.source import Source, SourceFrame, calibration_of
from arlight.sources.synthetic import make_sequence

SESSION_TIMESTAMP_STRIDE = 1e6  # seconds between two sessions' source timestamps
FRAME_PERIOD_S = 1 / 30  # source timestamps: base + i / 30
SMALL_OVERRIDES = {"volume_resolution": 64, "aux_resolution": 32}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


class ServerProcess:
    """`arlight serve` as a child process; its RSS sampled every `interval_s`."""

    def __init__(self, port: int, workers: int, log_path: str):
        self.port = port
        self.workers = workers
        self.log = open(log_path, "a")  # noqa: SIM115 - closed in close()
        self.proc: subprocess.Popen | None = None
        self.lives: list[list[tuple[float, float]]] = []  # per life: (monotonic s, RSS MB)
        self._stop = threading.Event()
        threading.Thread(target=self._sample, daemon=True).start()

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "arlight.cli",
                "serve",
                "--bind",
                f"tcp://127.0.0.1:{self.port}",
                "--workers",
                str(self.workers),
                "--heartbeat",
                "1",
                "--log-interval",
                "30",
                "--shutdown-grace",
                "10",
            ],
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        self.lives.append([])

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def terminate(self, timeout_s: float = 30.0) -> float:
        """SIGTERM; seconds until the process exited."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return time.monotonic() - t0

    def _sample(self, interval_s: float = 1.0) -> None:
        while not self._stop.wait(interval_s):
            proc = self.proc
            if proc is not None and proc.poll() is None:
                value = rss_mb(proc.pid)
                if value is not None:
                    self.lives[-1].append((time.monotonic(), value))

    def close(self) -> None:
        self._stop.set()
        self.log.close()


@dataclass
class SessionTally:
    name: str
    index: int
    generated: int = 0  # frames taken from the source
    received: set = field(default_factory=set)
    duplicates: int = 0
    out_of_order: int = 0
    mixed: int = 0  # a Result whose timestamp is not its frame's
    last_seq: int = -1
    final_errors: list = field(default_factory=list)
    reconnects: int = 0
    result_times: list = field(default_factory=list)  # monotonic s of each Result

    def on_result(self, result, _wall) -> None:
        self.result_times.append(time.monotonic())
        if result.seq in self.received:
            self.duplicates += 1
        if result.seq < self.last_seq:
            self.out_of_order += 1
        self.last_seq = max(self.last_seq, result.seq)
        self.received.add(result.seq)
        expected = self.index * SESSION_TIMESTAMP_STRIDE + result.seq * FRAME_PERIOD_S
        if abs(result.timestamp - expected) > 1e-6:
            self.mixed += 1

    def on_error(self, error: Error) -> None:
        self.final_errors.append(f"{error.seq}: {error.code} {error.field} {error.message}")


def looping_source(index: int, sequence, end_mono: float, tally: SessionTally) -> Source:
    """The synthetic frames (with their poses) over and over until `end_mono`."""
    cam = sequence.camera

    def frames():
        i = 0
        while time.monotonic() < end_mono:
            f = sequence.frames[i % len(sequence.frames)]
            tally.generated += 1
            yield SourceFrame(
                timestamp=index * SESSION_TIMESTAMP_STRIDE + i * FRAME_PERIOD_S,
                color=f.color,
                depth=f.depth,
                pose=f.pose,
            )
            i += 1

    return Source(
        f"soak{index}", calibration_of(cam), float(sequence.frames[0].depth_scale), 10**9, frames
    )


class Flood(threading.Thread):
    """A hostile peer: junk at `rate` messages per second, and budget-busting Hellos."""

    def __init__(self, address: str, rate: float, sequence, end_mono: float):
        super().__init__(daemon=True)
        self.address, self.rate, self.end_mono = address, rate, end_mono
        self.sent = 0
        self.replies = 0
        self.budget_hellos = 0
        self.budget_refused = 0
        self.budget_welcomed = 0
        f = sequence.frames[0]
        frame = Frame(0, 1.0, f.color, f.depth, None, None, "png", "zstd")
        self.frame = [bytes(memoryview(p)) for p in encode(frame)]
        cal = calibration_of(sequence.camera)
        big = calibration_of(type(sequence.camera).kinect_v1(2048, 2048))
        self.hellos = [
            encode(
                Hello(
                    PROTOCOL_VERSION,
                    SessionConfig(
                        session=f"hostile{i}",
                        role="capture",
                        calibration=c,
                        depth_scale=5000.0,
                        mode="lossless",
                        overrides=o,
                    ),
                )
            )
            for i, (c, o) in enumerate(
                [
                    (cal, {"robust_iterations": 1_000_000}),
                    (big, {}),
                    (cal, {"rt_directions": 10**7}),
                    (cal, {"block_count": "many"}),
                ]
            )
        ]

    def junk(self, rng: random.Random) -> list[bytes]:
        kind = rng.randrange(7)
        if kind == 6:  # issue 39: a header of many containers (the I/O thread parses it)
            nested = [[[]] * 500] * rng.randrange(50, 500)
            return [msgpack.packb({"v": PROTOCOL_VERSION, "type": "hello", "x": nested})]
        head = bytearray(self.frame[0])
        if kind == 0:
            return [rng.randbytes(rng.randrange(1, 200))]
        if kind == 1:
            return [bytes(head[: rng.randrange(len(head))]), *self.frame[1:]]
        if kind == 2:
            head[rng.randrange(len(head))] ^= 1 + rng.randrange(255)
            return [bytes(head), *self.frame[1:]]
        if kind == 3:  # a frame from no session, seq out of range
            header = msgpack.unpackb(self.frame[0])
            header["seq"] = rng.choice([2**63, 2**64 - 1, -5, 7])
            return [msgpack.packb(header, use_bin_type=True), *self.frame[1:]]
        if kind == 4:
            return self.frame[:-1]
        return [
            msgpack.packb(
                {
                    "v": PROTOCOL_VERSION,
                    "type": rng.choice(["hello", "frame", "result", "bye", "teleport"]),
                    "x": rng.random(),
                }
            )
        ]

    def run(self) -> None:
        ctx = zmq.Context.instance()
        rng = random.Random(0)
        peers = [ctx.socket(zmq.DEALER) for _ in range(4)]
        for p in peers:
            p.setsockopt(zmq.LINGER, 0)
            p.connect(self.address)
        next_hello = time.monotonic()
        while time.monotonic() < self.end_mono:
            t0 = time.monotonic()
            peer = peers[self.sent % len(peers)]
            try:
                if t0 >= next_hello:  # every 5 s: a Hello the budgets must refuse
                    hello = self.hellos[self.budget_hellos % len(self.hellos)]
                    hp = ctx.socket(zmq.DEALER)
                    hp.setsockopt(zmq.LINGER, 0)
                    hp.connect(self.address)
                    hp.send_multipart(hello, zmq.NOBLOCK)
                    self.budget_hellos += 1
                    if hp.poll(10000):
                        reply = decode(hp.recv_multipart())
                        if isinstance(reply, Welcome):
                            self.budget_welcomed += 1
                        elif isinstance(reply, Error):
                            self.budget_refused += 1
                    hp.close()
                    next_hello = t0 + 5.0
                peer.send_multipart(self.junk(rng), zmq.NOBLOCK)
                self.sent += 1
            except zmq.Again:
                pass
            for p in peers:
                while p.poll(0):
                    p.recv_multipart()
                    self.replies += 1
            time.sleep(max(0.0, 1.0 / self.rate - (time.monotonic() - t0)))
        for p in peers:
            p.close()


class StuckDisplay(threading.Thread):
    """A display that subscribes, heartbeats and never reads a Result."""

    def __init__(self, address: str, session: str, token: str, end_mono: float):
        super().__init__(daemon=True)
        self.address, self.session, self.end_mono = address, session, end_mono
        self.token = token  # the session's: the server refuses a display without it

    def run(self) -> None:
        ctx = zmq.Context.instance()
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.RCVHWM, 2)
        s.setsockopt(zmq.RCVBUF, 4096)
        s.connect(self.address)
        hello = encode(
            Hello(
                PROTOCOL_VERSION,
                SessionConfig(session=self.session, role="display", token=self.token),
            )
        )
        last_hello = 0.0
        while time.monotonic() < self.end_mono:
            now = time.monotonic()
            if now - last_hello > 10.0:  # again now and then: the server may have restarted
                s.send_multipart(hello)
                last_hello = now
            try:
                s.send_multipart(encode(Heartbeat(time.time())), zmq.NOBLOCK)
            except zmq.Again:
                pass
            time.sleep(0.5)
        s.close()


def summarise_rss(lives: list[list[tuple[float, float]]], warmup: float, stream_end: float) -> dict:
    """Per server life, while the clients streamed (up to `stream_end`, monotonic s): RSS at
    start, after warm-up, its peak after warm-up, at the end, and the slope after warm-up;
    `after_close_mb`: the last sample (the sessions closed)."""
    out = []
    for all_samples in lives:
        samples = [s for s in all_samples if s[0] <= stream_end]
        if not samples:
            continue
        t = np.array([s[0] for s in samples])
        r = np.array([s[1] for s in samples])
        after = t >= t[0] + warmup * (t[-1] - t[0])
        slope = (
            float(np.polyfit(t[after] - t[0], r[after], 1)[0] * 60) if after.sum() >= 3 else None
        )
        out.append(
            {
                "start_mb": round(float(r[0]), 1),
                "after_warmup_mb": round(float(r[after][0]), 1),
                "peak_after_warmup_mb": round(float(r[after].max()), 1),
                "end_mb": round(float(r[-1]), 1),
                "slope_after_warmup_mb_per_min": None if slope is None else round(slope, 2),
                "after_close_mb": round(float(all_samples[-1][1]), 1),
                "samples": int(len(r)),
            }
        )
    return {"lives": out}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--duration", type=float, default=600.0, help="seconds of streaming")
    parser.add_argument("--size", default="80x60", help="WxH of the frames")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--kill-at",
        type=float,
        default=0.5,
        help="fraction of the duration at which the server is SIGKILLed and restarted (0: never)",
    )
    parser.add_argument("--flood-rate", type=float, default=200.0)
    parser.add_argument("--stuck-displays", type=int, default=2)
    parser.add_argument(
        "--warmup",
        type=float,
        default=0.2,
        help="fraction of each server life counted as warm-up for RSS",
    )
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--log", default="soak-server.log", help="the server's log")
    args = parser.parse_args(argv)
    width, height = (int(x) for x in args.size.lower().split("x"))

    sequence = make_sequence(8, width, height)
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    server = ServerProcess(port, args.workers, args.log)
    server.start()
    time.sleep(2.0)  # the interpreter's start-up; the clients retry anyway
    t_start = time.monotonic()
    end = t_start + args.duration
    tallies = [SessionTally(f"soak{i}", i) for i in range(args.sessions)]
    clients = []
    for i, tally in enumerate(tallies):
        options = StreamOptions(
            server=address,
            session=tally.name,
            mode="lossless",
            rate="max",
            preset=args.preset,
            overrides=dict(SMALL_OVERRIDES),
            timestamps="source",
            reconnect_timeout_s=120.0,
            color_codec="png",
            depth_codec="zstd",
            client_name="soak",
        )
        client = CaptureClient(
            looping_source(i, sequence, end, tally),
            options,
            on_result=tally.on_result,
            on_error=tally.on_error,
        )
        box: dict = {}

        def run(client=client, box=box):
            try:
                box["summary"] = client.run()
            except BaseException as exc:  # noqa: BLE001 - reported below
                box["error"] = repr(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        clients.append((client, thread, box))
    flood = Flood(address, args.flood_rate, sequence, end) if args.flood_rate > 0 else None
    if flood:
        flood.start()
    for i in range(args.stuck_displays):
        StuckDisplay(
            address, tallies[i % len(tallies)].name, clients[i % len(tallies)][0].token, end
        ).start()
    watchers = []
    for tally, (client, _, _) in zip(tallies, clients, strict=True):
        seen: dict[int, int] = {}
        display = DisplayClient(
            DisplayOptions(
                server=address,
                session=tally.name,
                follow=True,
                token=client.token,
                reconnect_timeout_s=120.0,
                print_interval_s=3600.0,
                client_name="soak-display",
            ),
            on_result=lambda result, _record, seen=seen: seen.__setitem__(
                result.seq, seen.get(result.seq, 0) + 1
            ),
            printer=lambda _line: None,
        )
        threading.Thread(target=display.run, daemon=True).start()
        watchers.append((display, seen))

    killed_at = None
    if args.kill_at > 0:
        time.sleep(max(0.0, t_start + args.kill_at * args.duration - time.monotonic()))
        server.kill()
        killed_at = time.monotonic() - t_start
        print(f"soak: server SIGKILLed at {killed_at:.0f} s; restarting", flush=True)
        time.sleep(1.0)
        server.start()
    while time.monotonic() < end:
        time.sleep(1.0)
    for _client, thread, _ in clients:  # the sources end at `end`; the last frames finish
        thread.join(300)
    stuck_clients = sum(thread.is_alive() for _, thread, _ in clients)
    for client, thread, _ in clients:
        if thread.is_alive():
            client.stop()
    if flood:
        flood.join(30)
    time.sleep(1.0)
    for display, _ in watchers:
        display.stop()
    term_s = server.terminate()
    server.close()

    kill_mono = None if killed_at is None else t_start + killed_at

    def largest_gaps(times: list[float]) -> tuple[float | None, float | None]:
        """(largest gap between Results, the largest not spanning the kill and the 30 s
        after it: the server's restart and the clients' reconnect), seconds."""
        if len(times) < 2:
            return None, None
        pairs = list(zip(times[:-1], times[1:], strict=True))
        calm = [
            b - a for a, b in pairs if kill_mono is None or b < kill_mono or a > kill_mono + 30.0
        ]
        return round(max(b - a for a, b in pairs), 2), round(max(calm), 2) if calm else None

    per_session = []
    for tally, (_, _, box), (_, seen) in zip(tallies, clients, watchers, strict=True):
        gap, calm_gap = largest_gaps(tally.result_times)
        summary = box.get("summary")
        sent = tally.generated
        lost = sent - len(tally.received) - len(tally.final_errors)
        per_session.append(
            {
                "session": tally.name,
                "sent": sent,
                "received": len(tally.received),
                "lost": lost,
                "final_errors": len(tally.final_errors),
                "duplicated": tally.duplicates,
                "out_of_order": tally.out_of_order,
                "mixed": tally.mixed,
                "reconnects": summary.reconnects if summary else None,
                "largest_gap_s": gap,
                "largest_gap_outside_kill_s": calm_gap,
                "display_results": sum(seen.values()),
                "display_processed_twice": sum(n > 1 for n in seen.values()),
                "client_error": box.get("error"),
                "errors": tally.final_errors[:5],
            }
        )
    totals = {
        k: sum(s[k] for s in per_session)
        for k in ("sent", "received", "lost", "final_errors", "duplicated", "out_of_order", "mixed")
    }
    report = {
        "machine": {
            "host": platform.node(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "settings": vars(args),
        "elapsed_s": round(time.monotonic() - t_start, 1),
        "killed_at_s": killed_at,
        "sigterm_exit_s": round(term_s, 2),
        "clients_still_running": stuck_clients,
        "totals": totals,
        "frames_per_s": round(totals["received"] / args.duration, 2),
        "sessions": per_session,
        "rss": summarise_rss(server.lives, args.warmup, end),
        "flood": None
        if flood is None
        else {
            "sent": flood.sent,
            "replies": flood.replies,
            "budget_hellos": flood.budget_hellos,
            "budget_refused": flood.budget_refused,
            "budget_welcomed": flood.budget_welcomed,
        },
    }
    print(json.dumps(report, indent=1, default=str))
    print(
        f"soak: {args.sessions} sessions x {args.duration:.0f} s at {width}x{height} "
        f"({args.preset}): sent {totals['sent']}, received {totals['received']}, lost "
        f"{totals['lost']}, failed {totals['final_errors']}, duplicated "
        f"{totals['duplicated']}, out of order {totals['out_of_order']}, mixed "
        f"{totals['mixed']}; {report['frames_per_s']} Results/s; SIGTERM exit in "
        f"{term_s:.1f} s",
        flush=True,
    )
    gaps = [s["largest_gap_outside_kill_s"] for s in per_session if s["largest_gap_outside_kill_s"]]
    print(
        f"soak: largest gap between a session's Results (outside the kill): "
        f"{max(gaps) if gaps else None} s; per session {gaps}",
        flush=True,
    )
    print(
        f"soak: displays received {sum(s['display_results'] for s in per_session)} "
        f"Results; {sum(s['display_processed_twice'] for s in per_session)} frame(s) "
        "processed twice (in flight at the kill)",
        flush=True,
    )
    for i, life in enumerate(report["rss"]["lives"]):
        print(
            f"soak: server life {i + 1}: RSS start {life['start_mb']} MB, after warm-up "
            f"{life['after_warmup_mb']} MB, peak {life['peak_after_warmup_mb']} MB, end "
            f"{life['end_mb']} MB, slope {life['slope_after_warmup_mb_per_min']} MB/min; "
            f"{life['after_close_mb']} MB once the sessions closed"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1, default=str)
    bad = (
        totals["lost"]
        or totals["final_errors"]
        or totals["duplicated"]
        or totals["out_of_order"]
        or totals["mixed"]
        or stuck_clients
        or (flood is not None and flood.budget_welcomed)
        or any(s["display_results"] == 0 for s in per_session)
    )  # the displays watched
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
