"""The legitimate session beside an attack (issue 39): a lossless stream over a real loopback
socket that records when each Result arrives, so a test asserts its largest gap between
Results (the latency an attacker could add), not only that its frames were answered."""

from __future__ import annotations

import threading
import time

import zmq
from streaming_support import RawPeer, frame_parts

from arlight.protocols import Error, Heartbeat, Result, Welcome, decode, encode


class LegitStream:
    """A capture client streaming 64x48 lossless frames with `window` unacknowledged, from a
    thread, until `stop()`; `gaps_s()`: the seconds between its start, each Result and its
    stop. Heartbeats go out every 0.1 s, so a quiet moment is never taken for a dead peer."""

    def __init__(
        self,
        address: str,
        session: str = "legit",
        window: int = 2,
        peer: RawPeer | None = None,
        **hello,
    ):
        self.peer = RawPeer(address) if peer is None else peer
        welcome = self.peer.hello(session, mode="lossless", **hello)
        if not isinstance(welcome, Welcome):
            raise AssertionError(f"the legitimate session was refused: {welcome}")
        self.window = window
        self.result_times: list[float] = []
        self.errors: list[Error] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.start_mono = self.stop_mono = 0.0

    def __enter__(self) -> LegitStream:
        self.start_mono = time.monotonic()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        if not self._stop.is_set():
            self.stop_mono = time.monotonic()
            self._stop.set()
            self._thread.join(10)
            self.peer.close()

    def _run(self) -> None:
        sock = self.peer.socket
        seq = in_flight = 0
        next_beat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                sock.send_multipart(encode(Heartbeat(time.time())), zmq.NOBLOCK)
                next_beat = now + 0.1
            while in_flight < self.window:
                sock.send_multipart(frame_parts(seq, value=seq % 200), zmq.NOBLOCK)
                seq += 1
                in_flight += 1
            if not sock.poll(50):
                continue
            message = decode(sock.recv_multipart())
            if isinstance(message, Result):
                self.result_times.append(time.monotonic())
                in_flight -= 1
            elif isinstance(message, Error) and message.seq is not None:
                self.errors.append(message)
                in_flight -= 1

    def gaps_s(self) -> list[float]:
        """Seconds between the start, each Result and the stop (stop() first)."""
        marks = [self.start_mono, *self.result_times, self.stop_mono or time.monotonic()]
        return [b - a for a, b in zip(marks[:-1], marks[1:], strict=True)]

    def largest_gap_s(self) -> float:
        return max(self.gaps_s())

    def assert_served(self, limit_s: float = 3.0) -> None:
        """The stream got Results all along: no gap of `limit_s` seconds or more, no Error."""
        self.stop()
        assert not self.errors, self.errors[:3]
        assert len(self.result_times) >= 2, "the legitimate session got no Results"
        gap = self.largest_gap_s()
        assert gap < limit_s, f"the legitimate session waited {gap:.1f} s for a Result"


class ServerProcess:
    """tests/hostile_server.py in a child process: `address`, `alive()`, `close()` (which
    returns its exit code)."""

    def __init__(self, **options):
        import json
        import subprocess
        import sys
        from pathlib import Path

        script = Path(__file__).resolve().parent / "hostile_server.py"
        self.process = subprocess.Popen(
            [sys.executable, str(script), json.dumps(options)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.process.stdout is not None
        port = self.process.stdout.readline().strip()
        if not port.isdigit():
            self.process.kill()
            raise AssertionError(f"the server process did not start (printed {port!r})")
        self.address = f"tcp://127.0.0.1:{port}"

    def alive(self) -> bool:
        return self.process.poll() is None

    def close(self) -> int:
        if self.alive():
            assert self.process.stdin is not None
            self.process.stdin.close()
            try:
                return self.process.wait(30)
            except Exception:
                self.process.kill()
                raise
        return self.process.wait()


def curve_peer(
    address: str, keys_dir: str, name: str = "client", routing_id: bytes | None = None
) -> RawPeer:
    """A RawPeer speaking CURVE with the keys `arlight keys generate DIR` made (and the
    routing id it chose, if any)."""
    import zmq.auth

    server_public, _ = zmq.auth.load_certificate(f"{keys_dir}/server.key")
    public, secret = zmq.auth.load_certificate(f"{keys_dir}/{name}.key_secret")
    peer = RawPeer.__new__(RawPeer)
    peer.ctx = zmq.Context.instance()
    peer.socket = peer.ctx.socket(zmq.DEALER)
    peer.socket.setsockopt(zmq.LINGER, 0)
    peer.socket.curve_serverkey = server_public
    peer.socket.curve_publickey = public
    peer.socket.curve_secretkey = secret
    if routing_id is not None:
        peer.socket.setsockopt(zmq.ROUTING_ID, routing_id)
    peer.socket.connect(address)
    return peer
